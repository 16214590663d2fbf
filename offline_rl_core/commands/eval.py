"""`offline-rl eval`: success rate (Wilson 95 % CI) and final distance of a checkpoint, or of a
task's scripted expert, on any task's env."""

from __future__ import annotations

import argparse

from ..common.errors import UserError
from ..common.atomic import write_json_atomic
from ..evaluation.rollouts import evaluate_policy, format_rate
from ..common.output_paths import check_output_file
from ..serving.policy import load_policy
from ..common.seeds import HELD_OUT, seed_arg
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
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.episodes < 1:
        raise UserError(f"--episodes must be >= 1, got {args.episodes}")
    if args.json:
        check_output_file(args.json, "--json")
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
        print(f"wrote {args.json}")
    return 0
