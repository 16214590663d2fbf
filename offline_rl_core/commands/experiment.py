"""`offline-rl experiment`: the chapter's BC-vs-offline comparison, end to end."""

from __future__ import annotations

import argparse
import contextlib

from ..common.errors import RunFailed, UserError
from ..common.output_paths import check_output_dir
from ..common.seeds import seed_arg
from .sweep import add_engine_arguments, engine_of
from ..runs.experiment import ExperimentConfig, format_table, run_experiment, summary_rows, verdict
from ..task.envs import make_env
from ..task.spec import BUILTIN_DIR, load_task

OFFLINE_ALGOS = ("awac", "iql", "filtered_bc", "naive", "auto")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "experiment",
        help="the chapter's experiment: BC vs an offline learner, with confidence intervals",
        description="Collect the chapter's dataset, train BC and an offline learner on it, evaluate both on "
        "the same held-out episodes and report Wilson intervals per arm and Newcombe's interval for the gap. "
        "Writes DIR/metrics.json (DIR/seed_<s>/... and DIR/summary.md|png for several seeds). "
        "Training writes resume points every second, so a killed experiment loses little: rerun it with --resume.",
    )
    seeds = p.add_mutually_exclusive_group()
    seeds.add_argument("--seed", type=seed_arg, default=None, help="one experiment seed (default 0)")
    seeds.add_argument("--seeds", type=seed_arg, nargs="+", help="several seeds")
    p.add_argument("--algo", choices=OFFLINE_ALGOS, default=None,
                   help="offline learner compared with BC (default awac); auto: the learner and budget chosen from "
                        "each seed's dataset (README, 'The best prior')")
    p.add_argument("--naive", action="store_true", help="Break-It: naive max-Q instead of AWAC (same as --algo naive)")
    p.add_argument("--expert-frac", type=float, default=0.3, help="share of expert episodes in the dataset (default 0.3)")
    p.add_argument("--episodes", type=int, default=None, help="dataset episodes (default 200; smoke 20)")
    p.add_argument("--steps", type=int, default=None, help="gradient steps per learner (default 8000; smoke 400)")
    p.add_argument("--budget-s", type=float, default=None, metavar="S",
                   help="train the offline learner for about S seconds (steps from its measured rate; BC keeps "
                        "--steps); --algo auto's default is the chapter's AWAC loop time on this machine")
    p.add_argument("--smoke", action="store_true", help="the chapter's smoke settings: 20 episodes, 400 steps, "
                   "batch 64, hidden 64, 2 suites x 4 eval episodes")
    p.add_argument("--deterministic", action=argparse.BooleanOptionalAction, default=False,
                   help="fp32 everywhere (smoke always); the default runs the hidden layer in bf16 where that "
                        "measured clearly faster on this CPU (cached per machine, so later runs choose the same)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="training processes, one (learner, seed) run each; results do not depend on it "
                        "(default: one per CPU core; smoke: 1)")
    p.add_argument("--task", default=None, metavar="NAME_OR_FILE",
                   help="the task whose dataset is collected and on which both learners are evaluated: a built-in "
                        "task or a task file with a sim section (default: pusher_reach, the chapter's)")
    add_engine_arguments(p)
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--resume", action="store_true",
                   help="continue a killed experiment (same flags) from the resume points its training jobs left, "
                        "DIR/[seed_<s>/]resume_{bc,offline}.pt: same result, same bytes")
    p.add_argument("--resume-every", type=float, default=1.0, metavar="S",
                   help="seconds between each training job's resume points (default: %(default)s)")
    p.set_defaults(func=run)


def config_from_args(args: argparse.Namespace) -> ExperimentConfig:
    if args.naive and args.algo not in (None, "naive"):
        raise UserError(f"--naive conflicts with --algo {args.algo}; give one of them")
    algo = "naive" if args.naive else (args.algo or "awac")
    seeds = args.seeds if args.seeds else [0 if args.seed is None else args.seed]
    if len(set(seeds)) != len(seeds):
        raise UserError(f"--seeds has duplicates: {' '.join(map(str, seeds))}")
    if not 0.0 <= args.expert_frac <= 1.0:
        raise UserError(f"--expert-frac must be in [0, 1], got {args.expert_frac}")
    overrides = {"seeds": seeds, "algo": algo, "expert_frac": args.expert_frac, "deterministic": args.deterministic,
                 "budget_s": args.budget_s}
    if args.task is not None:
        task = load_task(args.task)
        make_env(task)  # a task no sim hosts: said before anything runs
        # a file by its path, so worker processes and a --resume read the same task
        overrides["task"] = str(task.path.resolve()) if task.path and task.path.parent != BUILTIN_DIR else task.name
    if args.budget_s is not None and not args.budget_s > 0:
        raise UserError(f"--budget-s must be > 0 seconds, got {args.budget_s}")
    overrides["engine"] = engine_of(args)
    if args.workers is not None:
        if args.workers < 1:
            raise UserError(f"--workers must be >= 1, got {args.workers}")
        if overrides["engine"] == "ray":
            raise UserError("--workers is for --engine local; on Ray each (learner, seed) run takes one of the cluster's CPUs")
        overrides["workers"] = args.workers
    for name in ("episodes", "steps"):
        value = getattr(args, name)
        if value is not None:
            if value < 1:
                raise UserError(f"--{name} must be >= 1, got {value}")
            overrides[name] = value
    return ExperimentConfig.smoke_settings(**overrides) if args.smoke else ExperimentConfig(**overrides)


def _engine(cfg: ExperimentConfig, address: str | None):
    """Ray connected for the block (``--engine ray``), or nothing to connect."""
    if cfg.engine != "ray":
        return contextlib.nullcontext()
    from ..runs.ray_engine import connected

    return connected(address)


def run(args: argparse.Namespace) -> int:
    check_output_dir(args.out, "--out")
    cfg = config_from_args(args)
    if args.resume_every <= 0:
        raise UserError(f"--resume-every must be > 0, got {args.resume_every}")
    try:
        with _engine(cfg, args.address):
            outcomes = run_experiment(cfg, args.out, log=lambda line: print(line, flush=True),
                                      resume=args.resume, resume_every=args.resume_every)
    except RunFailed as exc:
        raise RunFailed(f"{exc}; the same command with --resume continues from the last resume points") from None
    rows = summary_rows(cfg, outcomes)
    print()
    print(f"{cfg.mode} vs BC on {cfg.n_pooled} pooled held-out episodes per seed"
          f" (success with 95% Wilson CI; difference with Newcombe's CI)")
    print(format_table(cfg, rows))
    print()
    print(verdict(cfg, rows[-1]))
    if len(outcomes) > 1:
        print(f"wrote {args.out}/seed_<s>/metrics.json, {args.out}/summary.md, {args.out}/summary.png")
    else:
        print(f"wrote {outcomes[0].out_dir / 'metrics.json'}")
    return 0
