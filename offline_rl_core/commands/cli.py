"""`offline-rl`: the command line of the learning core.

Each subcommand lives in ``offline_rl_core/commands/<name>.py`` and exposes
``register(subparsers)``; that function adds its parser and sets ``func``.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from ..common.errors import RunFailed, UserError

# Order is the order shown by --help.
COMMAND_MODULES = (
    "collect",
    "bag_info",
    "bag",
    "dataset",
    "export_dataset",
    "import_dataset",
    "train",
    "eval",
    "experiment",
    "sweep",
    "export_onnx",
    "bench",
    "hil",
    "classifier",
    "weights_key",
    "sros2",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="offline-rl",
        description="Offline RL from rosbag2 logs of the pusher-reach arm: collect, inspect, train, evaluate.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(f"offline_rl_core.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"offline_rl_core.commands.{name}":
                continue  # command not part of this build
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        result = args.func(args)
    except (UserError, RunFailed) as exc:
        print(f"offline-rl: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except OSError as exc:  # a path that could not be written or read: name it, no traceback
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"offline-rl: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return UserError.exit_code
    except KeyboardInterrupt:
        print("offline-rl: interrupted", file=sys.stderr)
        return 130
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
