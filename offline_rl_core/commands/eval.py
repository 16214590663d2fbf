"""`offline-rl eval`: success rate (Wilson 95 % CI) and final distance of a checkpoint, or of a
task's scripted expert, on any task's env."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..common.errors import UserError
from ..common.atomic import write_json_atomic
from ..evaluation.rollouts import evaluate_policy, format_rate
from ..common.output_paths import check_output_file
from ..serving.policy import load_policy
from ..common.seeds import HELD_OUT, seed_arg
from ..runs.loggers import DEFAULT_LOGGER, LOGGERS, check_logger, eval_scalars, open_logger
from ..task.envs import make_env
from ..task.spec import DEFAULT_TASK, load_task


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "eval",
        help="roll a checkpoint (or the task's scripted expert) out on held-out reset seeds",
        description="Roll a checkpoint, or with --expert the task's scripted expert, out for N episodes on "
        "reset seeds SEED..SEED+N-1 of a task's env and report the success rate with its 95 % Wilson interval "
        "and the mean final distance.",
    )
    who = p.add_mutually_exclusive_group(required=True)
    who.add_argument("--checkpoint", help="policy checkpoint (.pt, or a directory holding policy.pt, such as a "
                     "train --out DIR)")
    who.add_argument("--expert", action="store_true", help="the task's scripted expert instead of a checkpoint")
    p.add_argument("--task", default=DEFAULT_TASK, metavar="NAME_OR_FILE",
                   help=f"a built-in task or a task file with a sim section (default: {DEFAULT_TASK})")
    p.add_argument("--episodes", type=int, default=100, help="episodes to roll out (default 100)")
    p.add_argument("--seed", type=seed_arg, default=HELD_OUT, help=f"first reset seed (default {HELD_OUT}, the held-out range)")
    p.add_argument("--json", metavar="OUT", help="also write the results as JSON to OUT")
    p.add_argument("--sequential", action="store_true", help="pusher_reach: one env at a time (reference loop) "
                   "instead of batched (other tasks always run one env at a time)")
    p.add_argument("--logger", choices=LOGGERS, default=DEFAULT_LOGGER,
                   help="with --json: also log the results (eval/success_rate, its Wilson bounds, ...) at the "
                        "checkpoint's training step, beside OUT: tensorboard (event files in OUT's directory), "
                        "wandb (there in wandb/), or none (default: %(default)s)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.episodes < 1:
        raise UserError(f"--episodes must be >= 1, got {args.episodes}")
    if args.json:
        check_output_file(args.json, "--json")
        check_logger(args.logger)
    task = load_task(args.task)
    make_env(task)  # a task no sim hosts: said before the checkpoint is read
    policy = None if args.expert else load_policy(args.checkpoint, task)
    result = evaluate_policy(policy, args.episodes, args.seed, batched=not args.sequential,
                             checkpoint=None if args.expert else str(args.checkpoint), task=task)
    if task.name != DEFAULT_TASK:
        print(f"task            {task.name} ({task.source_file()}, digest {task.digest})")
    if args.expert:
        print("policy          the task's scripted expert")
    else:
        print(f"checkpoint      {args.checkpoint} ({policy.algorithm})")
    print(f"reset seeds     {args.seed}..{args.seed + args.episodes - 1}")
    print(f"success         {format_rate(result['successes'], result['episodes'])}  (95% Wilson CI)")
    print(f"mean final dist {result['mean_final_dist']:.4f} m")
    print(f"mean return     {result['mean_return']:.3f}")
    if args.json:
        write_json_atomic(args.json, result)
        log_results(args, policy, result)
        print(f"wrote {args.json}")
    return 0


def log_results(args: argparse.Namespace, policy, result: dict) -> None:
    """The results as curve points beside the JSON: at the step the checkpoint was trained
    to (its config's steps; an online learner's transitions), so evaluations of a run's
    checkpoints line up with its training curves; the scripted expert's (``policy`` None) at 0."""
    checkpoint = getattr(policy, "checkpoint", None) or {}
    step = int(checkpoint.get("trained_through") or (checkpoint.get("config") or {}).get("steps") or 0)
    who = "the task's scripted expert" if policy is None else str(args.checkpoint)
    settings = {"checkpoint": who, "algorithm": "expert" if policy is None else policy.algorithm,
                "task": args.task, "episodes": args.episodes, "seed": args.seed}
    out = Path(args.json)
    # resume: add to the event files there (a training run's, when OUT is in its directory)
    with open_logger(args.logger, out.parent, name=out.stem, resume=True, config=settings) as curves:
        curves.scalars(step, eval_scalars(result))
        curves.hparams(settings, eval_scalars(result))
