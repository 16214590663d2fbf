"""`offline-rl export --minari ID BAG`: a bag's transitions as a Minari dataset."""

from __future__ import annotations

import warnings

from ..data.bag import read_transitions
from ..data.interop import episode_runs, minari_root, to_minari
from ..data.task_record import check_layout_fits, task_of_bag


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export",
        help="write a bag's transitions as a Minari dataset (minari.load_dataset(ID) opens it)",
        description="Write the /pusher/transition messages of BAG as the Minari dataset ID, under "
        "MINARI_DATASETS_PATH (default ~/.minari/datasets): one Minari episode per run of rows with one "
        "episode id (a step lost in recording starts another), observations, actions, rewards, terminations "
        "and truncations, the task's spaces (Box observations, actions in [-1, 1]), and each step's episode "
        "id, step, source and success in the episode's infos, so `offline-rl import --minari ID OUT` gives "
        "the same rows back. An existing ID is refused.",
    )
    p.add_argument("--minari", required=True, metavar="ID",
                   help="Minari dataset ID, [NAMESPACE/]NAME-vN (e.g. pusher/mix-v0)")
    p.add_argument("bag", metavar="BAG", help="rosbag2 bag (directory, .db3 or .mcap) with /pusher/transition")
    p.add_argument("--task", metavar="NAME_OR_FILE",
                   help="the bag's task (default: the one it records, else pusher_reach); a pusher_reach dataset "
                        "names its Gymnasium env")
    p.add_argument("--description", help="the dataset's description (default: where it came from)")
    p.add_argument("--author", help="the dataset's author, for its metadata")
    p.add_argument("--author-email", help="the author's e-mail, for its metadata")
    p.add_argument("--code-permalink", help="link to the code that made the data, for its metadata")
    p.set_defaults(func=run)


def run(args) -> int:
    task = task_of_bag(args.bag, args.task)
    data = read_transitions(args.bag)
    check_layout_fits(args.bag, data.layout.obs_dim, data.layout.act_dim, task)
    description = args.description or (
        f"pusher-rl transitions of task {task.name} (digest {task.digest}) exported from the rosbag2 bag {args.bag}")
    with warnings.catch_warnings():
        # Minari asks for the metadata not given; the flags above give it
        warnings.filterwarnings("ignore", category=UserWarning, module=r"minari\.utils")
        path = to_minari(data, args.minari, description=description, task=task, author=args.author,
                         author_email=args.author_email, code_permalink=args.code_permalink)
    print(f"wrote the Minari dataset {args.minari} ({path}; root {minari_root()}): {len(data)} transitions, "
          f"{len(episode_runs(data))} episodes")
    return 0
