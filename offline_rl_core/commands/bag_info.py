"""`offline-rl bag-info`: `ros2 bag info` for any rosbag2 bag, plus its dataset summary."""

from __future__ import annotations

from pathlib import Path

from ..data.bag import bag_info

HELP = "show a bag's files, topics and counts, and its transitions per source"
DESCRIPTION = (
    "Print what `ros2 bag info` prints for any rosbag2 bag (a directory, or a .db3/.mcap file), "
    "whatever its message types; when it has /pusher/transition, also the transitions, episodes "
    "and mean return per source (expert, random, policy, human)."
)


def add_info_parser(subparsers, name: str):
    """The info command's parser: `bag-info` here, `bag info` in commands/bag.py."""
    parser = subparsers.add_parser(name, help=HELP, description=DESCRIPTION)
    parser.add_argument("path", type=Path, help="bag directory, or .db3/.mcap file")
    parser.set_defaults(func=lambda args: _run(args.path))
    return parser


def register(subparsers) -> None:
    add_info_parser(subparsers, "bag-info")


def _run(path: Path) -> int:
    print(bag_info(path).format())
    return 0
