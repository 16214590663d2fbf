"""``ros2``: hand over to a usable ros2cli (handover.py), else the verbs this project needs.

Implemented here (same output shape as ros2cli):
  ros2 run [--prefix P] PKG [EXE] [args ...]   (EXE may be left out when PKG has one)
  ros2 pkg executables [PKG] [--full-path] | list | prefix PKG
  ros2 topic list [-t] | echo TOPIC [TYPE] [--once] ... | hz TOPIC [--window N]
  ros2 launch PKG FILE.launch.yaml [name:=value ...]
  ros2 node list [-a]
  ros2 param list [NODE] | get NODE NAME | set NODE NAME VALUE | describe NODE NAME ...
  ros2 bag info BAG
``ros2 run`` replaces this process with the executable (``exec``), so the pid the
user started is the node's pid and signals reach the node directly.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys

from . import ament
from .handover import hand_over, say_once, usable_ros2cli

PROG = "ros2"


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    usable, why_not = usable_ros2cli()
    if usable:
        return hand_over(argv)
    if why_not:
        say_once(why_not)
    if not argv:
        print(_usage(), file=sys.stderr)
        return 2
    if argv[0] in ("-h", "--help"):
        print(_usage())
        print(__doc__.split("\n\n", 1)[1].rstrip())
        return 0
    verb, rest = argv[0], argv[1:]
    try:
        if verb == "run":
            return run_command(rest)
        if verb == "pkg":
            return pkg_command(rest)
        if verb == "topic":
            from .topic import topic_command

            return topic_command(rest)
        if verb == "launch":
            from .launch import launch_command

            return launch_command(rest)
        if verb in ("node", "param"):
            from .node_param import node_command, param_command

            return (node_command if verb == "node" else param_command)(rest)
        if verb == "bag":
            return bag_command(rest)
    except KeyboardInterrupt:
        return 0
    print(_usage(), file=sys.stderr)
    print(f"{PROG}: error: unknown command '{verb}' (this shim implements run, launch, pkg, topic, node, param, bag)", file=sys.stderr)
    return 2


def _usage() -> str:
    return f"usage: {PROG} {{run,launch,pkg,topic,node,param,bag}} ..."


# ---------------------------------------------------------------- run
RUN_USAGE = "usage: ros2 run [-h] [--prefix PREFIX] package_name [executable_name] ..."


def run_command(args: list[str]) -> int:
    prefix_cmd: list[str] = []
    while args and args[0].startswith("-"):
        if args[0] in ("-h", "--help"):
            print(RUN_USAGE)
            print("\nRun a package specific executable (the executable name may be left out when the package has one).")
            return 0
        if args[0] == "--prefix" and len(args) >= 2:
            prefix_cmd = shlex.split(args[1])
            args = args[2:]
        elif args[0].startswith("--prefix="):
            prefix_cmd = shlex.split(args[0].split("=", 1)[1])
            args = args[1:]
        else:
            break
    if not args:
        print(RUN_USAGE, file=sys.stderr)
        print("ros2 run: error: the following arguments are required: package_name", file=sys.stderr)
        return 2
    package, rest = args[0], args[1:]
    exes = ament.executables(package)
    if exes is None:
        print(f"Package '{package}' not found", file=sys.stderr)
        return 1
    if rest and rest[0] in exes:
        name, rest = rest[0], rest[1:]
    elif len(exes) == 1 and (not rest or rest[0].startswith("-")):
        name = next(iter(exes))
    elif not rest:
        print(RUN_USAGE, file=sys.stderr)
        print(
            f"ros2 run: error: package '{package}' has {len(exes)} executables "
            f"({', '.join(exes) or 'none'}); name one",
            file=sys.stderr,
        )
        return 2
    else:
        print("No executable found", file=sys.stderr)
        return 1
    path = str(exes[name])
    cmd = [*prefix_cmd, path, *rest]
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        os.execvp(cmd[0], cmd)  # the node takes over this pid
    except OSError as exc:
        print(f"ros2 run: error: cannot execute {path}: {exc.strerror}", file=sys.stderr)
        return 1
    return 0  # not reached


# ---------------------------------------------------------------- pkg
def pkg_command(args: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="ros2 pkg", description="Various package related sub-commands")
    sub = parser.add_subparsers(dest="verb", metavar="Commands")
    exe_p = sub.add_parser("executables", help="Output a list of package specific executables")
    exe_p.add_argument("package_name", nargs="?")
    exe_p.add_argument("--full-path", action="store_true", help="Show the full path of each executable")
    sub.add_parser("list", help="Output a list of available packages")
    prefix_p = sub.add_parser("prefix", help="Output the prefix path of a package")
    prefix_p.add_argument("package_name")
    opts = parser.parse_args(args)
    if opts.verb == "list":
        for name in sorted(ament.packages()):
            print(name)
        return 0
    if opts.verb == "prefix":
        prefix = ament.package_prefix(opts.package_name)
        if prefix is None:
            print("Package not found", file=sys.stderr)
            return 1
        print(prefix)
        return 0
    if opts.verb == "executables":
        names = [opts.package_name] if opts.package_name else sorted(ament.packages())
        for name in names:
            exes = ament.executables(name)
            if exes is None:
                print("Package not found", file=sys.stderr)
                return 1
            for exe, path in exes.items():
                print(path if opts.full_path else f"{name} {exe}")
        return 0
    parser.print_help()
    return 2


# ---------------------------------------------------------------- bag
def bag_command(args: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="ros2 bag", description="Various rosbag related sub-commands")
    sub = parser.add_subparsers(dest="verb", metavar="Commands")
    info_p = sub.add_parser("info", help="Print information about a bag to the screen")
    info_p.add_argument("bag_path", help="Bag to open (a directory, or a .db3 / .mcap file)")
    info_p.add_argument("-s", "--storage", default="", help="Storage implementation of the bag (detected)")
    if not args or args[0] not in ("info", "-h", "--help"):  # record, play, ...: say what to use instead
        parser.print_usage(sys.stderr)
        verb = f"'{args[0]}' is not implemented here; " if args else ""
        print(f"ros2 bag: error: {verb}this shim implements 'info'; record with 'ros2 run recorder node'",
              file=sys.stderr)
        return 2
    opts = parser.parse_args(args)
    try:
        from offline_rl_core.data.bag import bag_info
        from offline_rl_core.common.errors import UserError
    except ImportError as exc:
        print(f"ros2 bag info: error: offline_rl_core.data.bag is not importable ({exc})", file=sys.stderr)
        return 1
    try:
        print(bag_info(opts.bag_path).format())
    except UserError as exc:
        print(f"ros2 bag info: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
