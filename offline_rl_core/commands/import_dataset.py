"""`offline-rl import --minari ID OUT`: a Minari dataset as a rosbag2 bag of transitions."""

from __future__ import annotations

from pathlib import Path

from ..data.bag import write_transitions
from ..data.bag.info import summarize_sources
from ..data.bag.paths import check_replaceable, resolve_target
from ..data.interop import from_minari, minari_root
from ..data.transitions import SOURCE_BY_NAME
from ..task.spec import DEFAULT_TASK, load_task


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "import",
        help="write a Minari dataset as a rosbag2 bag of /pusher/transition messages",
        description="Read the Minari dataset ID from MINARI_DATASETS_PATH (default ~/.minari/datasets) and "
        "write its transitions as the bag OUT (x.db3 or x.mcap, else a bag directory), for `offline-rl train "
        "--bag OUT` and the nodes. Each step's next observation is the episode's next one; who acted, episode "
        "ids, steps and success come from the episodes' infos where the dataset has them (pusher-rl's exports "
        "do), else --source, Minari's episode ids, 0.. and false. Observations and actions must be flat Box "
        "spaces of the task's sizes (--task, default pusher_reach; a task other than pusher_reach is recorded in "
        "the bag), actions within [-1, 1]. An existing bag at OUT is replaced atomically; any "
        "other existing file or directory is refused.",
    )
    p.add_argument("--minari", required=True, metavar="ID", help="Minari dataset ID (e.g. pusher/mix-v0)")
    p.add_argument("out", metavar="OUT", type=Path, help="bag to write")
    p.add_argument("--source", choices=sorted(SOURCE_BY_NAME),
                   help="who acted, for a dataset whose infos do not say (e.g. expert for a D4RL expert set)")
    p.add_argument("--task", default=DEFAULT_TASK, metavar="NAME_OR_FILE",
                   help="the dataset's task: a built-in task or a task file (default: %(default)s)")
    p.add_argument("--storage", choices=("sqlite3", "mcap"), default=None,
                   help="storage of a bag directory (default: from the suffix, else sqlite3)")
    p.set_defaults(func=run)


def run(args) -> int:
    target = resolve_target(args.out, args.storage)  # a bad OUT is refused before the dataset is read
    check_replaceable(target, overwrite=True)
    task = load_task(args.task)
    data = from_minari(args.minari, None if args.source is None else SOURCE_BY_NAME[args.source], task)
    recorded = {} if task.name == DEFAULT_TASK else {"task": task}  # as offline-rl collect records it
    write_transitions(target.path, data, storage=target.storage,
                      custom_data={"offline_rl.import": f"minari {args.minari} from {minari_root()}"}, **recorded)
    print(f"wrote {target.path} ({target.storage}): {len(data)} transitions from the Minari dataset {args.minari}")
    for s in summarize_sources(data):
        print(f"  {s.source}: {s.episodes} episodes, {s.transitions} transitions, mean return {s.mean_return:.3f}")
    return 0
