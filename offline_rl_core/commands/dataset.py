"""`offline-rl dataset --from-topics SPEC IN_BAG OUT_BAG`: transitions from raw robot topics."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..common.atomic import write_text_atomic
from ..data.bag import write_transitions
from ..data.bag.info import summarize_sources
from ..data.bag.paths import resolve_target
from ..common.errors import UserError
from ..common.output_paths import check_output_file
from ..data.raw_topics import load_spec, transitions_from_topics

REPORT_KEY = "offline_rl.dataset"  # the bag's custom metadata entry holding the join report (JSON)

DESCRIPTION = """\
Build a /pusher/transition dataset from what a robot logs: its joint states
(sensor_msgs/JointState), its commands (JointState effort, or std_msgs/Float64MultiArray
torques scaled by the spec) and its goal (geometry_msgs/PointStamped), joined by stamp
as the YAML spec says, with the pusher's reward and success rule. The fingertip comes
from a fingertip topic when the bag has one, else from the joints' planar kinematics.
Episodes start where the target moves, after a reset message or after a time gap. Who
acted is the command topic (pusher/command/expert, .../random, .../policy, .../human).

Every message is accounted for: duplicate stamps, commands joined exactly or within the
tolerance, commands dropped (no state near them, another command nearer the same state,
no next state) are counted, printed and stored in OUT_BAG's custom metadata under
"offline_rl.dataset" (--report FILE also writes them as JSON). Nothing is filled in.

The shipped example spec, bags/pusher_topics.yaml, lists every field with its default
and what it does: the sim's topics (/pusher/state, /pusher/command and
/pusher/command/<source>, /pusher/target, /pusher/fingertip), joints shoulder and elbow,
the nearest stamp within 5 ms, 50 Hz control. `offline-rl train --from-topics SPEC
--bag IN_BAG` (and the trainer node) train on such a bag directly.
"""


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "dataset",
        help="build a transition bag from raw robot topics (JointState, commands, goal)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--from-topics", required=True, metavar="SPEC", type=Path,
                        help="YAML spec naming the topics, joints and join rules (e.g. bags/pusher_topics.yaml)")
    parser.add_argument("in_bag", metavar="IN_BAG", type=Path, help="rosbag2 bag of raw topics (directory, .db3 or .mcap)")
    parser.add_argument("out_bag", metavar="OUT_BAG", type=Path,
                        help="bag to write with /pusher/transition: x.db3 or x.mcap (single file), else a bag directory")
    parser.add_argument("--storage", choices=("sqlite3", "mcap"), default=None,
                        help="storage of a bag directory (default: from the suffix, else sqlite3)")
    parser.add_argument("--report", metavar="FILE", type=Path, help="also write the join report as JSON here")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing OUT_BAG")
    parser.set_defaults(func=run)


def run(args) -> int:
    spec = load_spec(args.from_topics)
    target = resolve_target(args.out_bag, args.storage)
    if target.path.resolve() == args.in_bag.resolve():
        raise UserError(f"{args.out_bag}: OUT_BAG is the input bag; write the transitions to another path")
    if (target.path.exists() or target.path.is_symlink()) and not args.overwrite:
        raise UserError(f"{target.path} exists already; pass --overwrite to replace it")
    if args.report:
        check_output_file(args.report, "--report")  # before OUT_BAG is written
    data, report = transitions_from_topics(args.in_bag, spec)
    text = json.dumps(report.as_dict(), sort_keys=True)
    write_transitions(target.path, data, storage=target.storage, custom_data={REPORT_KEY: text})
    if args.report:
        write_text_atomic(args.report, json.dumps(report.as_dict(), indent=2) + "\n")
    print(report.format())
    print(f"wrote {target.path}: {len(data)} transitions in {report.episodes} episodes")
    for s in summarize_sources(data):
        print(f"  {s.source}: {s.episodes} episodes, {s.transitions} transitions, mean return {s.mean_return:.3f}")
    return 0
