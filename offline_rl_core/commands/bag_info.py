"""`offline-rl bag-info`: `ros2 bag info` for any rosbag2 bag, plus its dataset summary."""

from __future__ import annotations

from pathlib import Path

from ..bag import bag_info


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "bag-info",
        help="show a bag's files, topics and counts, and its transitions per source",
        description=(
            "Print what `ros2 bag info` prints for any rosbag2 bag (a directory, or a .db3/.mcap file), "
            "whatever its message types; when it has /pusher/transition, also the transitions, episodes "
            "and mean return per source (expert, random, policy, human)."
        ),
    )
    parser.add_argument("path", type=Path, help="bag directory, or .db3/.mcap file")
    parser.set_defaults(func=lambda args: _run(args.path))


def _run(path: Path) -> int:
    print(bag_info(path).format())
    return 0
