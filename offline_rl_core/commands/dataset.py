"""`offline-rl dataset [--task TASK] IN_BAG OUT_BAG`: transitions from raw robot topics."""

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
from ..data.raw_topics import transitions_from_topics
from ..data.task_record import chosen_task, task_of_bag

REPORT_KEY = "offline_rl.dataset"  # the bag's custom metadata entry holding the join report (JSON)

DESCRIPTION = """\
Build a transition dataset from what a robot logs (a plain `ros2 bag record`), as a task
file says: the joint states (sensor_msgs/JointState, the task's joints by name, in any
order), the commands (the task's controller topic, std_msgs/Float64MultiArray in the
controller's joint order or JointState, mapped back to actions in [-1, 1]; and the
project's own action topics), the goal (PointStamped, PoseStamped or a JointState goal)
and tracked points (from their topics, else forward kinematics), joined by stamp, with
the task's observation, reward and success. Episodes start where the goal moves, after a
reset message, after a time gap or at the time limit (episodes.max_steps).

Every message is accounted for: duplicate stamps, commands joined exactly or within the
tolerance, commands dropped (no state near them, another command nearer the same state,
no next state) are counted, printed and stored in OUT_BAG's custom metadata under
"offline_rl.dataset" (--report FILE also writes them as JSON). Nothing is filled in.

TASK is a built-in task (pusher_reach, the default; see offline_rl_core/task/builtin/,
whose pusher_reach.yaml documents every field) or a task file. A bag that records its task
(/task_description) needs none. `offline-rl train --from-topics --bag IN_BAG` (and the
trainer node) train on such a bag directly.
"""


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "dataset",
        help="build a transition bag from raw robot topics (JointState, commands, goal) as a task file says",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--task", metavar="TASK", help="built-in task name or task file (default: the task the bag "
                        "records, else pusher_reach)")
    parser.add_argument("--from-topics", metavar="TASK", default=None,
                        help="the same as --task (this command always builds from the topics)")
    parser.add_argument("in_bag", metavar="IN_BAG", type=Path, help="rosbag2 bag of raw topics (directory, .db3 or .mcap)")
    parser.add_argument("out_bag", metavar="OUT_BAG", type=Path,
                        help="bag to write with /pusher/transition: x.db3 or x.mcap (single file), else a bag directory")
    parser.add_argument("--storage", choices=("sqlite3", "mcap"), default=None,
                        help="storage of a bag directory (default: from the suffix, else sqlite3)")
    parser.add_argument("--success", metavar="CLASSIFIER", type=Path,
                        help="a success classifier (`offline-rl classifier train`) judges each state's success, for "
                        "the reward's bonus and the episode's end, instead of the task's success distance (which "
                        "the report still counts beside it)")
    parser.add_argument("--report", metavar="FILE", type=Path, help="also write the join report as JSON here")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing OUT_BAG")
    parser.set_defaults(func=run)


def run(args) -> int:
    task = chosen_task(args.task, args.from_topics)
    target = resolve_target(args.out_bag, args.storage)
    if target.path.resolve() == args.in_bag.resolve():
        raise UserError(f"{args.out_bag}: OUT_BAG is the input bag; write the transitions to another path")
    if (target.path.exists() or target.path.is_symlink()) and not args.overwrite:
        raise UserError(f"{target.path} exists already; pass --overwrite to replace it")
    if args.report:
        check_output_file(args.report, "--report")  # before OUT_BAG is written
    task = task_of_bag(args.in_bag, task)
    judge = None
    if args.success is not None:
        from ..learners.success_classifier import load_classifier

        judge = load_classifier(args.success, task)  # one line for no classifier or another task's
    data, report = transitions_from_topics(args.in_bag, task, judge=judge)
    text = json.dumps(report.as_dict(), sort_keys=True)
    write_transitions(target.path, data, storage=target.storage, custom_data={REPORT_KEY: text}, task=task)
    if args.report:
        write_text_atomic(args.report, json.dumps(report.as_dict(), indent=2) + "\n")
    print(report.format())
    print(f"wrote {target.path}: {len(data)} transitions in {report.episodes} episodes")
    for s in summarize_sources(data):
        print(f"  {s.source}: {s.episodes} episodes, {s.transitions} transitions, mean return {s.mean_return:.3f}")
    return 0
