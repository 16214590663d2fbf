"""`offline-rl collect`: roll out a task's dataset (the chapter's by default) and write it as a rosbag2 bag."""

from __future__ import annotations

import sys
from pathlib import Path

from ..data.bag import write_transitions
from ..data.bag.info import summarize_sources
from ..data.bag.paths import check_replaceable, resolve_target
from ..data.collect import collect_transitions, expert_episode_count
from ..common.errors import UserError
from ..common.seeds import seed_arg
from ..task.envs import make_env
from ..task.spec import DEFAULT_TASK, load_task


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "collect",
        help="roll out expert + random episodes in the sim and write them as a rosbag2 bag",
        description=(
            "Roll out EPISODES episodes of a task (pusher-reach by default; the first round(EXPERT_FRAC * "
            "EPISODES) by the task's scripted expert, the rest uniform-random actions) and write one "
            "/pusher/transition message per step. A task other than pusher_reach is recorded in the bag "
            "on /task_description. The same arguments always give the same bytes."
        ),
    )
    parser.add_argument("--task", default=DEFAULT_TASK, metavar="NAME_OR_FILE",
                        help="a built-in task (pusher_reach, pusher7_reach) or a task file with a sim section "
                             f"(default: {DEFAULT_TASK})")
    parser.add_argument("--episodes", type=int, default=200, help="episodes to roll out (default: 200)")
    parser.add_argument("--expert-frac", type=float, default=0.3, help="fraction of expert episodes (default: 0.3)")
    parser.add_argument("--seed", type=seed_arg, default=0, help="episode ep resets with seed + ep (default: 0)")
    parser.add_argument(
        "--out", required=True, type=Path,
        help="bag to write: x.db3 or x.mcap (single file), else a bag directory; an existing bag is replaced "
             "atomically, any other existing file or directory is refused",
    )
    parser.add_argument("--storage", choices=("sqlite3", "mcap"), default=None,
                        help="storage of a bag directory (default: from the suffix, else sqlite3)")
    parser.set_defaults(func=run)


def run(args) -> int:
    if args.episodes < 1:
        raise UserError(f"--episodes must be at least 1, got {args.episodes}")
    if not 0.0 <= args.expert_frac <= 1.0:
        raise UserError(f"--expert-frac must be in [0, 1], got {args.expert_frac}")
    target = resolve_target(args.out, args.storage)  # refuse a bad --out before rolling out
    check_replaceable(target, overwrite=True)  # an existing bag is replaced; anything else is kept
    task = load_task(args.task)
    make_env(task)  # a task no sim hosts, or a bad sim section: said now, in one line
    n_expert = expert_episode_count(args.episodes, args.expert_frac)
    print(
        f"collect: {args.episodes} episodes ({n_expert} expert, {args.episodes - n_expert} random), seed {args.seed}"
        + ("" if task.name == DEFAULT_TASK else f", task {task.name}"),
        file=sys.stderr,
    )
    every = max(1, args.episodes // 10)

    def progress(done: int, total: int) -> None:
        if done % every == 0 or done == total:
            print(f"collect: {done}/{total} episodes", file=sys.stderr, flush=True)

    transitions = collect_transitions(args.episodes, args.expert_frac, args.seed, progress=progress, task=task)
    recorded = {} if task.name == DEFAULT_TASK else {"task": task}  # pusher_reach: the chapter's bytes
    write_transitions(
        target.path, transitions, storage=target.storage,
        custom_data={
            "offline_rl.collect": f"episodes={args.episodes} expert_frac={args.expert_frac} seed={args.seed}"
                                  + ("" if task.name == DEFAULT_TASK else f" task={task.name}"),
        },
        **recorded,
    )
    size = target.path.stat().st_size if target.single_file else sum(p.stat().st_size for p in target.path.iterdir())
    print(f"wrote {target.path} ({target.storage}, {size / 2**20:.1f} MiB): "
          f"{len(transitions)} transitions, {args.episodes} episodes")
    for s in summarize_sources(transitions):
        print(f"  {s.source}: {s.episodes} episodes, {s.transitions} transitions, mean return {s.mean_return:.3f}")
    return 0
