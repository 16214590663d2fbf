"""One training run from bags to files: what `offline-rl train` and the trainer node do.

Reads one or more rosbag2 bags, trains one learner, evaluates it on held-out
resets, and writes ``DIR/policy.pt`` (atomic), ``DIR/metrics.json`` and
``DIR/training_curve.png``. Everything is validated before anything is written, so a
bad bag or flag leaves the output directory as it was.

The run's task is ``--task`` or the one the bags record (``data.task_record``), else
pusher_reach; every bag's transitions must have its sizes. The checkpoint records it
(``checkpoint["task"]``); metrics.json names it for tasks other than pusher_reach (whose
metrics keep the chapter's bytes).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import fields
from pathlib import Path
from typing import Callable

import torch

from ..common import seeds
from ..common.seeds import seed_arg
from ..data.fleet import bag_summary, expand_bags, read_fleet
from ..common.errors import UserError
from ..common.atomic import write_json_atomic
from ..common.output_paths import check_output_dir
from ..evaluation.rollouts import evaluate_policy
from ..learners import ALGORITHMS, Progress, TrainConfig, train
from ..learners.config import CHOICES
from ..learners.resume import ResumePoints
from .loggers import DEFAULT_LOGGER, LOGGER_HELP, LOGGERS, check_logger, eval_scalars, open_logger, progress_logger
from .plots import plot_training_curve
from .prior import plan_training
from ..serving.checkpoint import load_checkpoint, save_checkpoint
from ..data.raw_topics import transitions_from_topics
from ..data.task_record import check_layout_fits, chosen_task, task_of_bag
from ..data.transitions import Transitions
from ..serving.policy import policy_for_task
from ..task.spec import DEFAULT_TASK, TaskSpec, load_task

DEFAULT_EVAL_SEED = seeds.HELD_OUT
_CONFIG_FIELDS = {f.name for f in fields(TrainConfig)}


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags of `offline-rl train` and `ros2 run trainer node`: TrainConfig's fields."""
    d = TrainConfig()
    parser.add_argument("--bag", action="append", required=True, metavar="PATH",
                        help="rosbag2 bag (directory, .db3 or .mcap) with /pusher/transition; repeat to merge bags")
    parser.add_argument("--from-topics", metavar="TASK", nargs="?", const=True, default=None,
                        help="build the transitions from each bag's raw robot topics as the task file says "
                             "(see `offline-rl dataset --help`); `--from-topics TASK` is `--from-topics --task TASK`")
    parser.add_argument("--task", metavar="NAME_OR_FILE",
                        help="the task of the bags: a built-in task (pusher_reach, ...) or a task file (YAML); "
                             "default: the one the bags record, else pusher_reach")
    parser.add_argument("--algo", choices=ALGORITHMS + ("auto",), default=d.algo,
                        help="learner; auto: chosen from what the bag holds, trained for --budget-s "
                             "(README, 'The best prior') (default: %(default)s)")
    parser.add_argument("--steps", type=int, default=None,
                        help=f"gradient steps (default: {d.steps}, or what --budget-s allows)")
    parser.add_argument("--budget-s", type=float, default=None, metavar="S",
                        help="train for about S seconds: converted to steps before training from the learner's step "
                             "rate on this machine (measured once, cached), and recorded in metrics.json; "
                             "--algo auto's default is the chapter's AWAC loop time on this machine")
    parser.add_argument("--seed", type=seed_arg, default=0, help="seed of init and batch sampling (default: %(default)s)")
    parser.add_argument("--out", metavar="DIR",
                        help="output directory for policy.pt, metrics.json, training_curve.png (default: runs/ALGO-seedS)")
    parser.add_argument("--eval-episodes", type=int, default=100,
                        help="held-out rollouts after training, 0 to skip (default: %(default)s)")
    parser.add_argument("--eval-seed", type=seed_arg, default=DEFAULT_EVAL_SEED,
                        help="first reset seed of the evaluation rollouts (default: %(default)s)")
    parser.add_argument("--init", metavar="CHECKPOINT", help="warm-start policy (and critics if stored) from a checkpoint")
    parser.add_argument("--resume", action="store_true",
                        help="continue from DIR/resume.pt, the resume point a killed run left (same result, same bytes)")
    parser.add_argument("--resume-every", type=float, default=1.0, metavar="S",
                        help="seconds between resume points (default: %(default)s)")
    parser.add_argument("--logger", choices=LOGGERS, default=DEFAULT_LOGGER, help=LOGGER_HELP)
    groups = {"run": parser, "hyper-parameters": parser.add_argument_group("hyper-parameters (defaults are the chapter's)")}
    for f in fields(TrainConfig):
        if f.name in ("algo", "steps"):
            continue  # above, with their own choices and help
        flag, default = "--" + f.name.replace("_", "-"), getattr(d, f.name)
        options = dict(default=default, help=f.metadata["help"] + (" (default: %(default)s)" if default is not None else ""))
        if isinstance(default, bool):
            options["action"] = argparse.BooleanOptionalAction
        elif f.name in CHOICES:
            options["choices"] = CHOICES[f.name]
        else:
            options["type"] = type(default) if default is not None else (f.metadata.get("kind") or float)
        groups[f.metadata["group"]].add_argument(flag, **options)


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """The flags as a TrainConfig; for ``--algo auto`` the learner is a placeholder until
    ``prior.plan_training`` has seen the bag."""
    values = {k: v for k, v in vars(args).items() if k in _CONFIG_FIELDS}
    if values.get("steps") is None:
        values.pop("steps", None)
    if values.get("algo") == "auto":
        values["algo"] = TrainConfig.algo
    try:
        return TrainConfig(**values)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def task_of_run(paths: list[str], given: str | os.PathLike | TaskSpec | None = None) -> TaskSpec:
    """The task of a run on ``paths`` (bags, directories of bags or globs): ``given`` (which
    every bag that records a task must agree with), else the one they record (the same for
    all), else pusher_reach."""
    paths = expand_bags(paths)
    tasks = [task_of_bag(path, given) for path in paths]
    for path, task in zip(paths[1:], tasks[1:]):
        if task.digest != tasks[0].digest:
            raise UserError(f"{path}: the bag is of task {task.name} (digest {task.digest}), {paths[0]} of "
                            f"{tasks[0].name} (digest {tasks[0].digest}); train on one task's bags")
    return tasks[0] if tasks else load_task(given)


def load_bags(paths: list[str], from_topics: bool | str | None = None,
              task: str | os.PathLike | TaskSpec | None = None,
              workers: int | None = None) -> tuple[Transitions, list[dict]]:
    """Read and merge bags; episode ids are offset so they stay unique per bag. A path may
    be a directory of bags or a glob (a fleet, ``data/fleet.py``): its bags are decoded in
    ``workers`` processes (default: as many as pay for themselves).
    ``from_topics``: build the transitions from each bag's raw topics as its task says (a
    task name or file here is the same as ``task``). ``task``: the task of the bags (default:
    the one each bag records, else pusher_reach); the transitions must have its sizes (one
    line naming the bag otherwise)."""
    if isinstance(from_topics, (str, os.PathLike)):
        task = chosen_task(task, from_topics)
    paths = expand_bags(paths)
    if not from_topics:
        data, summary = read_fleet(paths, workers)
        if task is not None:
            check_layout_fits(paths[0] if len(paths) == 1 else f"{len(paths)} bags ({paths[0]}, ...)",
                              data.layout.obs_dim, data.layout.act_dim, load_task(task))
        return data, summary
    parts, summary, offset = [], [], 0
    for path in paths:
        of_bag = task_of_bag(path, task)
        data, report = transitions_from_topics(path, of_bag)
        if parts and data.layout != parts[0].layout:
            raise UserError(f"{path}: its transitions ({data.layout.describe()}) are not those of {paths[0]} "
                            f"({parts[0].layout.describe()}); train on bags of one task")
        data.episode = data.episode - data.episode.min() + offset
        offset = int(data.episode.max()) + 1
        parts.append(data)
        entry = {**bag_summary(path, data), "from_topics": report.as_dict()}
        if report.estop_dropped is not None:
            entry["estop_dropped"] = report.estop_dropped
        summary.append(entry)
    return (parts[0] if len(parts) == 1 else Transitions.concatenate(parts)), summary


def estop_dropped_of(summaries: list[dict]) -> int | None:
    """Transitions left out of the bags for the e-stop (``decode_bag``), or None where no bag
    records one."""
    counts = [s["estop_dropped"] for s in summaries if "estop_dropped" in s]
    return sum(counts) if counts else None


def console_progress(stream=None) -> Callable[[Progress], None]:
    """Progress lines on ``stream`` (default: sys.stderr as it is when a line is printed)."""
    def report(p: Progress) -> None:
        rate = p.step / p.elapsed_s if p.elapsed_s > 0 else 0.0
        eta = (p.total - p.step) / rate if rate > 0 else 0.0
        losses = "  ".join(f"{k} {v:.4g}" for k, v in p.scalars.items())
        print(f"  step {p.step:>6}/{p.total}  {rate:6.0f} steps/s  eta {eta:5.0f}s  {losses}", file=stream or sys.stderr, flush=True)
    return report


def run_training(
    bags: list[str],
    cfg: TrainConfig,
    seed: int,
    out_dir: str | os.PathLike,
    eval_episodes: int = 100,
    eval_seed: int = DEFAULT_EVAL_SEED,
    init: str | None = None,
    progress: Callable[[Progress], None] | None = None,
    log: Callable[[str], None] = lambda s: print(s, file=sys.stderr),
    resume: bool = False,
    resume_every: float = 1.0,
    from_topics: bool | str | None = None,
    auto: bool = False,
    budget_s: float | None = None,
    steps: int | None = None,
    task: str | os.PathLike | TaskSpec | None = None,
    dataset: tuple[Transitions, list[dict]] | None = None,
    decode_workers: int | None = None,
    logger: str = DEFAULT_LOGGER,
) -> Path:
    """Train ``cfg`` on the bags and write the run's files to ``out_dir``. ``auto``: the
    learner is the one ``prior.plan_training`` picks for the bag; ``auto`` or ``budget_s``:
    as many steps as the budget allows, unless ``steps`` is given (then ``steps``).
    ``task``: the bags' task (default: the one they record, else pusher_reach).
    ``dataset``: the bags already read (``load_bags(bags)``'s result, e.g. handed to the run
    by a sweep's engine); else they are read here, in ``decode_workers`` processes.
    ``logger``: where the curves go besides metrics.json (``loggers``): the losses and
    steps/s while training, the evaluation, the settings and results as hyper-parameters."""
    out = check_output_dir(out_dir, "--out")
    check_logger(logger)
    if eval_episodes < 0:
        raise UserError(f"--eval-episodes must be >= 0, got {eval_episodes}")
    if isinstance(from_topics, (str, os.PathLike)):
        task = chosen_task(task, from_topics)
    task = task_of_run(bags, task)
    if dataset is not None:
        data, bags_read = dataset
        check_layout_fits(bags[0], data.layout.obs_dim, data.layout.act_dim, task)
    else:
        data, bags_read = load_bags(bags, from_topics, task, decode_workers)
    cfg, plan = plan_training(data, cfg, auto, budget_s, steps, log, task)  # task: where episodes end at the goal
    init_ckpt = None
    if init:
        init_ckpt = load_checkpoint(init)
        policy_for_task(init_ckpt, init, task)  # a warm start of another task: one line naming both
        if int(init_ckpt["hidden"]) != cfg.hidden:
            raise UserError(f"{init}: checkpoint hidden size {init_ckpt['hidden']} differs from --hidden {cfg.hidden}")
    if resume_every <= 0:
        raise UserError(f"--resume-every must be > 0, got {resume_every}")
    points = ResumePoints(out / "resume.pt", resume_every, resume)
    if resume:
        log(f"resuming from {points.path}" if points.path.exists() else f"no resume point at {points.path}; starting")
    estop_dropped = estop_dropped_of(bags_read)
    if estop_dropped is not None:
        log(f"left out {estop_dropped} transitions recorded while the e-stop was engaged")
    log(f"training {cfg.algo} on {len(data)} transitions from {len(bags)} bag(s), {cfg.steps} steps, seed {seed}")
    with open_logger(logger, out, name=out.name, resume=resume, config=cfg.to_dict()) as curves:
        # UserError: a bad resume point
        result = train(data, cfg, seed, progress=progress_logger(curves, then=progress), init=init_ckpt, resume=points,
                       task=task)
        _check_finite(result.checkpoint, cfg, points)
        metrics = _metrics(cfg, seed, data, bags_read, result, init, plan, task)
        if eval_episodes and not task.sim:
            log(f"no held-out rollouts: no sim hosts task {task.name}")
        elif eval_episodes:
            log(f"evaluating on {eval_episodes} held-out rollouts "
                f"(reset seeds {eval_seed}..{eval_seed + eval_episodes - 1})")
            metrics["eval"] = evaluate_policy(result.policy, eval_episodes, eval_seed, task=task)
            curves.scalars(cfg.steps, eval_scalars(metrics["eval"]))
        curves.hparams({"algorithm": cfg.algo, "seed": seed, "task": task.name, "transitions": len(data),
                        "init": metrics["init"], "config": cfg.to_dict()}, _hparam_metrics(metrics))
    result.checkpoint["metrics"] = metrics
    out.mkdir(parents=True, exist_ok=True)
    save_checkpoint(out / "policy.pt", result.checkpoint)
    write_json_atomic(out / "metrics.json", metrics)
    plot_training_curve(result.history, out / "training_curve.png", title=f"{cfg.algo} seed {seed}")
    points.done()  # the run is complete: its resume point is spent
    curves.drop_previous()
    return out


def _metrics(cfg: TrainConfig, seed: int, data: Transitions, bags_read: list[dict], result, init: str | None,
             plan: dict | None, task: TaskSpec) -> dict:
    """metrics.json of a run, before its evaluation."""
    metrics: dict = {
        "algorithm": cfg.algo,
        "seed": seed,
        "steps": cfg.steps,
        "transitions": len(data),
        "bags": bags_read,
        "dataset_hash": result.checkpoint["dataset_hash"],
        "config": cfg.to_dict(),
        "init": str(init) if init else None,
        "final_losses": {k: round(float(v[-1]), 6) for k, v in result.history.items() if k != "step"},
        "mean_abs_q": None if result.mean_abs_q is None else round(result.mean_abs_q, 6),
    }
    estop_dropped = estop_dropped_of(bags_read)
    if estop_dropped is not None:  # only bags that record the e-stop: the others' metrics keep their bytes
        metrics["estop_dropped"] = estop_dropped
    if plan is not None:
        metrics["plan"] = plan  # what --algo auto / --budget-s decided, and from what
    if task.digest != load_task(DEFAULT_TASK).digest:  # pusher_reach's metrics keep the chapter's bytes
        metrics["task"] = task.layout()
    return metrics


def _hparam_metrics(metrics: dict) -> dict[str, float]:
    """The results a run is compared on in TensorBoard's HParams tab: its final losses and
    its evaluation, under the tags they were logged as."""
    out = {f"train/{k}": v for k, v in metrics["final_losses"].items()}
    out.update(eval_scalars(metrics["eval"]) if "eval" in metrics else {})
    return out


def _check_finite(checkpoint: dict, cfg: TrainConfig, points: ResumePoints) -> None:
    """Refuse to write weights the loader would refuse: a diverged run keeps the previous
    checkpoint (and its spent resume point goes; resuming would diverge again)."""
    bad = [name for name, tensor in checkpoint["policy_state"].items() if not bool(torch.isfinite(tensor).all())]
    if bad:
        points.done()
        raise UserError(f"{cfg.algo} diverged: policy weight '{bad[0]}' is not finite after {cfg.steps} steps; "
                        f"nothing written but the event files of its curves (try a smaller --lr or --beta)")


def default_out_dir(algo: str, seed: int) -> str:
    return f"runs/{algo}-seed{seed}"


def run_training_from_args(args: argparse.Namespace, progress: Callable[[Progress], None] | None = None) -> Path:
    cfg = config_from_args(args)
    out = args.out or default_out_dir(args.algo, args.seed)
    return run_training(args.bag, cfg, args.seed, out, args.eval_episodes, args.eval_seed, args.init,
                        progress=progress or console_progress(), resume=args.resume, resume_every=args.resume_every,
                        from_topics=args.from_topics, auto=args.algo == "auto", budget_s=args.budget_s,
                        steps=args.steps, task=args.task, logger=getattr(args, "logger", DEFAULT_LOGGER))


def summary_line(out: Path) -> str:
    metrics = json.loads((out / "metrics.json").read_text())
    line = f"wrote {out / 'policy.pt'}"
    ev = metrics.get("eval")
    if ev:
        line += (f"  success {ev['success_rate']:.2f} [{ev['wilson_ci_lo']:.2f}, {ev['wilson_ci_hi']:.2f}]"
                 f"  mean final dist {ev['mean_final_dist']:.4f} m over {ev['episodes']} rollouts")
    return line
