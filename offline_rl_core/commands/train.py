"""`offline-rl train`: fit a learner on one or more bags."""

from __future__ import annotations

from ..runs.training_run import add_train_arguments, run_training_from_args, summary_line


def _run(args) -> int:
    out = run_training_from_args(args)
    print(summary_line(out))
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "train",
        help="train BC / filtered BC / AWAC / IQL / naive / SAC (or auto: chosen from the bag) on rosbag2 bags",
        description="Train a policy on the /pusher/transition messages of one or more rosbag2 bags. "
        "Writes DIR/policy.pt, DIR/metrics.json and DIR/training_curve.png.",
    )
    add_train_arguments(p)
    p.set_defaults(func=_run)
