"""`offline-rl eval`: success rate (Wilson 95 % CI) and final distance of a checkpoint."""

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
    policy = load_policy(args.checkpoint)
    result = evaluate_policy(policy, args.episodes, args.seed, batched=not args.sequential, checkpoint=str(args.checkpoint))
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
    checkpoints line up with its training curves."""
    checkpoint = policy.checkpoint if hasattr(policy, "checkpoint") else {}
    step = int(checkpoint.get("trained_through") or (checkpoint.get("config") or {}).get("steps") or 0)
    out = Path(args.json)
    # resume: add to the event files there (a training run's, when OUT is in its directory)
    with open_logger(args.logger, out.parent, name=out.stem, resume=True,
                     config={"checkpoint": str(args.checkpoint)}) as curves:
        curves.scalars(step, eval_scalars(result))
        curves.hparams({"checkpoint": str(args.checkpoint), "algorithm": policy.algorithm, "episodes": args.episodes,
                        "seed": args.seed}, eval_scalars(result))
