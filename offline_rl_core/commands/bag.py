"""`offline-rl bag info|repair PATH`: inspect a bag, or make one cut off by a kill whole."""

from __future__ import annotations

from pathlib import Path

from ..data.bag import repair_bag
from .bag_info import add_info_parser


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "bag",
        help="bag tools: info (like `ros2 bag info`), repair (like `ros2 bag reindex` / `mcap recover`)",
        description="Tools for rosbag2 bags: a bag directory (its metadata.yaml may be missing), or a .db3/.mcap file.",
    )
    sub = parser.add_subparsers(dest="bag_command", metavar="SUBCOMMAND")
    sub.required = True
    add_info_parser(sub, "info")
    repair = sub.add_parser(
        "repair",
        help="make a bag whose recorder was killed whole again, in place",
        description=(
            "Repair a bag in place after its writer was killed: fold an sqlite write-ahead log into the "
            ".db3 file and rewrite its metadata; cut a truncated .mcap file after its last whole record and "
            "write its summary (like `mcap recover`); for a bag directory, repair every storage file and "
            "rebuild metadata.yaml from them (like `ros2 bag reindex`). Every step can be run again if "
            "interrupted. A bag still being recorded is refused."
        ),
    )
    repair.add_argument("path", type=Path, help="bag directory, or .db3/.mcap file")
    repair.set_defaults(func=lambda args: _repair(args.path))


def _repair(path: Path) -> int:
    done = repair_bag(path)
    for line in done:
        print(f"{path}: {line}")
    if not done:
        print(f"{path}: nothing to repair")
    return 0
