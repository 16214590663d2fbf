"""`offline-rl eval`: success rate (Wilson 95 % CI) and final distance of a checkpoint."""

from __future__ import annotations

import argparse

from ..common.errors import UserError
from ..common.atomic import write_json_atomic
from ..evaluation.rollouts import evaluate_policy, format_rate
from ..common.output_paths import check_output_file
from ..serving.policy import load_policy
from ..common.seeds import HELD_OUT, seed_arg


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "eval",
        help="roll a checkpoint out on held-out reset seeds",
        description="Roll a checkpoint out for N episodes on reset seeds SEED..SEED+N-1 and report "
        "the success rate with its 95 % Wilson interval and the mean final distance.",
    )
    p.add_argument("--checkpoint", required=True, help="policy checkpoint (.pt, or a directory holding policy.pt, such as a train --out DIR)")
    p.add_argument("--episodes", type=int, default=100, help="episodes to roll out (default 100)")
    p.add_argument("--seed", type=seed_arg, default=HELD_OUT, help=f"first reset seed (default {HELD_OUT}, the held-out range)")
    p.add_argument("--json", metavar="OUT", help="also write the results as JSON to OUT")
    p.add_argument("--sequential", action="store_true", help="one env at a time (reference loop) instead of batched")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.episodes < 1:
        raise UserError(f"--episodes must be >= 1, got {args.episodes}")
    if args.json:
        check_output_file(args.json, "--json")
    policy = load_policy(args.checkpoint, "pusher_reach")  # the rollouts run pusher_reach's env
    result = evaluate_policy(policy, args.episodes, args.seed, batched=not args.sequential, checkpoint=str(args.checkpoint))
    print(f"checkpoint      {args.checkpoint} ({policy.algorithm})")
    print(f"reset seeds     {args.seed}..{args.seed + args.episodes - 1}")
    print(f"success         {format_rate(result['successes'], result['episodes'])}  (95% Wilson CI)")
    print(f"mean final dist {result['mean_final_dist']:.4f} m")
    print(f"mean return     {result['mean_return']:.3f}")
    if args.json:
        write_json_atomic(args.json, result)
        print(f"wrote {args.json}")
    return 0
