"""`offline-rl classifier`: a success classifier from labelled episodes (train), and its error rates (eval)."""

from __future__ import annotations

import argparse
import json

from ..common.atomic import write_json_atomic
from ..common.errors import UserError
from ..common.output_paths import check_output_file
from ..common.seeds import seed_arg
from ..learners.success_classifier import ClassifierConfig, load_classifier
from ..runs.classifier_run import LABEL_SOURCES, score_on_bags, train_from_bags

LABELS_HELP = ("where each episode's label comes from: its bag's episode_label topic (a person's keys or gamepad), "
               "the simulator's success at the episode's end, or auto: the topic where a bag has one "
               "(default: %(default)s)")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "classifier", help="train a success classifier from labelled episodes, or score one",
        description="A success classifier judges from the task's observation whether a state is a success, "
        "so that the online stage can learn without a simulator saying so (hil --online --success FILE).")
    sub = p.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    d = ClassifierConfig()
    t = sub.add_parser("train", help="train one on the labelled episodes of bags",
                       description="Train a small MLP on the task's observations: the last --tail states of each "
                       "success-labelled episode are successes, every state of a failure-labelled one a failure. "
                       "Writes OUT (a checkpoint-like file that records its task).")
    t.add_argument("--bag", action="append", required=True, metavar="PATH", help="a bag of labelled episodes (repeatable)")
    t.add_argument("--out", required=True, metavar="FILE", help="the classifier file to write")
    t.add_argument("--labels", choices=LABEL_SOURCES, default="auto", help=LABELS_HELP)
    t.add_argument("--successes", type=int, help="train on the first N success-labelled episodes only")
    t.add_argument("--failures", type=int, help="train on the first N failure-labelled episodes only")
    t.add_argument("--task", metavar="NAME_OR_FILE", help="the bags' task (default: the one they record, else pusher_reach)")
    t.add_argument("--seed", type=seed_arg, default=0, help="seed of the weights and batches (default: %(default)s)")
    t.add_argument("--steps", type=int, default=d.steps, help="gradient steps (default: %(default)s)")
    t.add_argument("--tail", type=int, default=d.tail, help="last states of a success that are successes (default: %(default)s)")
    t.add_argument("--head", type=int, default=d.head,
                   help="first states of every episode that are failures, a success's too (for a task whose "
                   "resets never start at the goal; default: %(default)s, only a failure's states)")
    t.add_argument("--threshold", type=float, default=d.threshold,
                   help="probability from which a state is judged a success (default: %(default)s)")
    t.set_defaults(func=_train)
    e = sub.add_parser("eval", help="false-positive and false-negative rates on labelled episodes",
                       description="Judge the last state of each labelled episode of the bags and compare with its label.")
    e.add_argument("--classifier", required=True, metavar="FILE")
    e.add_argument("--bag", action="append", required=True, metavar="PATH")
    e.add_argument("--labels", choices=LABEL_SOURCES, default="auto", help=LABELS_HELP)
    e.add_argument("--json", metavar="OUT", help="also write the rates as JSON")
    e.set_defaults(func=_eval)


def _count(name: str, value):
    if value is not None and value < 1:
        raise UserError(f"--{name} must be >= 1, got {value}")


def _train(args: argparse.Namespace) -> int:
    for name in ("successes", "failures", "steps", "tail"):
        _count(name, getattr(args, name))
    if args.head < 0:
        raise UserError(f"--head must be >= 0, got {args.head}")
    if not 0.0 < args.threshold < 1.0:
        raise UserError(f"--threshold must be between 0 and 1, got {args.threshold}")
    check_output_file(args.out, "--out")
    cfg = ClassifierConfig(steps=args.steps, tail=args.tail, head=args.head, threshold=args.threshold)
    contents = train_from_bags(args.bag, args.out, cfg, args.seed, args.labels, args.successes, args.failures,
                               args.task)
    print(json.dumps({"out": args.out, **contents["trained_on"]}))
    return 0


def _eval(args: argparse.Namespace) -> int:
    if args.json:
        check_output_file(args.json, "--json")
    from ..data.task_record import task_of_bag

    result = score_on_bags(load_classifier(args.classifier, task_of_bag(args.bag[0])), args.bag, args.labels)
    print(json.dumps(result))
    if args.json:
        write_json_atomic(args.json, {"classifier": args.classifier, "bags": args.bag, **result})
    return 0
