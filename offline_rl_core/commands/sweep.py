"""`offline-rl sweep`: many training runs from one spec, on worker processes or on Ray."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from ..common.errors import RunFailed, UserError
from ..runs.local_engine import LocalEngine
from ..runs.sweep import finished_runs, format_arms, format_runs, load_sweep_spec, run_sweep

ENGINES = ("local", "ray")


def add_engine_arguments(p: argparse.ArgumentParser) -> None:
    """--engine and --address, as `sweep` and `experiment` take them."""
    p.add_argument("--engine", choices=ENGINES, default=None,
                   help="local: worker processes of this machine (default); ray: Ray tasks, on a private Ray of this "
                        "machine or on the cluster at --address (needs the ray extra)")
    p.add_argument("--address", metavar="auto|HOST:PORT",
                   help="the Ray cluster to run on: auto (the one `ray start` runs on this machine) or its head's "
                        "HOST:PORT; implies --engine ray")


def engine_of(args: argparse.Namespace) -> str:
    if args.address and args.engine == "local":
        raise UserError("--address names a Ray cluster; it goes with --engine ray, not --engine local")
    return "ray" if args.address or args.engine == "ray" else "local"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sweep",
        help="many training runs from one YAML spec (learners x hyper-parameters x bags x seeds), locally or on Ray",
        description="Train every run a sweep spec names (README, 'Sweeps and fleets'), each as `offline-rl train` "
        "would into DIR/<run>/, evaluate each on the same held-out rollouts, and report Wilson intervals per run "
        "and arm and Newcombe's interval against the spec's baseline: DIR/results.jsonl (one row per run), "
        "DIR/summary.md, DIR/summary.png. A run that fails is reported with its error and stops no other; "
        "--resume runs only the runs not finished.",
    )
    p.add_argument("spec", metavar="SPEC.yaml", help="the sweep spec")
    add_engine_arguments(p)
    p.add_argument("--out", metavar="DIR", help="output directory (default: runs/sweep-NAME, NAME the spec's name)")
    p.add_argument("--resume", action="store_true",
                   help="continue a sweep in DIR: skip its finished runs (metrics.json beside a run.json equal to "
                        "the run's spec), run the rest")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local engine: worker processes, one run each (default: one per CPU core)")
    p.add_argument("--shared-bags", action="store_true",
                   help="ray engine: every machine sees the bags at the same path (shared storage), so they are "
                        "decoded anywhere in the cluster (default: on this machine, which then sends the datasets)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    spec = load_sweep_spec(args.spec)  # every field and bag checked before anything starts
    engine = engine_of(args)
    if args.workers is not None:
        if args.workers < 1:
            raise UserError(f"--workers must be >= 1, got {args.workers}")
        if engine == "ray":
            raise UserError("--workers is for --engine local; on Ray each run takes one of the cluster's CPUs")
    if args.shared_bags and engine != "ray":
        raise UserError("--shared-bags is for --engine ray")
    out = Path(args.out or f"runs/sweep-{re.sub(r'[^A-Za-z0-9_.-]', '_', spec.name)}")
    finished_runs(spec, out, args.resume)  # a DIR that cannot take the sweep: said before Ray starts
    log = lambda line: print(line, flush=True)  # noqa: E731
    if engine == "ray":
        from ..runs.ray_engine import RayEngine, connected

        with connected(args.address):
            outcome = run_sweep(spec, out, RayEngine(args.shared_bags, log), args.resume, log)
    else:
        outcome = run_sweep(spec, out, LocalEngine(args.workers), args.resume, log)
    print()
    print("Arms, pooled over seeds (success with 95% Wilson CI"
          + (f"; difference to {spec.baseline} with Newcombe's CI)" if spec.baseline else ")"))
    print(format_arms(outcome))
    print()
    print(format_runs(outcome))
    print(f"wrote {out / 'results.jsonl'}, {out / 'summary.md'}, {out / 'summary.png'}")
    if outcome.failed:
        for row in outcome.failed:
            print(f"failed: {row['name']}: {row['error']}")
        raise RunFailed(f"{len(outcome.failed)} of {len(outcome.rows)} runs failed (listed above); "
                        "the same command with --resume runs them again")
    return 0
