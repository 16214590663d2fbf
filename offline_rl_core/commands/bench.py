"""`offline-rl bench`: speed figures against the reference implementations."""

from __future__ import annotations

import argparse
import os
import sys

from ..common.errors import UserError
from ..common.output_paths import check_output_file


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "bench",
        help="benchmark training, bag decoding, evaluation, serving and recording against references",
        description="Measure each figure next to its reference in the same run (the chapter's training loop, "
        "d3rlpy, rosbags' per-message deserialize, the sequential evaluation loop, a bare rclpy echo node), "
        "print a table and optionally write JSON. d3rlpy rows need the 'bench' extra; ROS rows need the 'ros' "
        "extra and the nodes. Timings on a shared machine are noisy: compare the ratios.",
    )
    p.add_argument("--quick", action="store_true", help="short runs (under 3 minutes on 2 cores)")
    p.add_argument("--json", metavar="PATH", help="write the results as JSON")
    p.add_argument("--only", metavar="GROUPS", help="comma-separated subset of train,decode,eval,serve,record,online,sweep,fleet")
    p.add_argument("--threads", type=int, default=None,
                   help="threads for every contender: torch's for the references, the step's for ours (default: each one's own default)")
    p.add_argument("--device", default="cpu",
                   help="where the training figures train: cpu (default), or cuda / cuda:N; every contender "
                        "trains there, d3rlpy and the chapter loop included")
    p.add_argument("--isa", choices=("native", "avx2"), default="native",
                   help="instruction set every contender's kernels may use: native (default: all this CPU has), "
                        "or avx2, capping torch's, oneDNN's and MKL's kernels at AVX2/FMA as on a CPU without "
                        "AVX-512 (the clock and caches stay this CPU's)")
    p.add_argument("--markdown", action="store_true", help="print the table as markdown")
    p.add_argument("--tiny", action="store_true", help=argparse.SUPPRESS)  # tests: every path, tiny sizes
    p.set_defaults(func=run)


def _rerun_with_isa_cap(isa: str) -> None:
    """Start this command again with the kernels capped at ``isa``: the libraries read
    their caps once, when they load, so the environment must be set before that."""
    from ..common.machine import ISA_LIMIT_ENV

    if isa == "native" or all(os.environ.get(k) == v for k, v in ISA_LIMIT_ENV.items()):
        return
    env = {**os.environ, **ISA_LIMIT_ENV}
    print(f"bench: capping the kernels at {isa.upper()} ({' '.join(f'{k}={v}' for k, v in ISA_LIMIT_ENV.items())})",
          flush=True)
    os.execve(sys.executable, [sys.executable, "-m", "offline_rl_core.commands.cli", *sys.argv[1:]], env)


def run(args: argparse.Namespace) -> int:
    from ..common.atomic import write_json_atomic
    from ..benchmarks.harness import GROUPS, BenchSettings, format_table, run_bench

    _rerun_with_isa_cap(args.isa)

    only = None
    if args.only is not None:
        only = [g.strip() for g in args.only.split(",") if g.strip()]
        if not only:
            raise UserError(f"--only: expected some of {', '.join(GROUPS)} (comma-separated), got '{args.only}'")
        unknown = [g for g in only if g not in GROUPS]
        if unknown:
            raise UserError(f"--only: unknown group(s) {', '.join(unknown)}; expected some of {', '.join(GROUPS)}")
    if args.threads is not None and args.threads < 1:
        raise UserError(f"--threads must be >= 1, got {args.threads}")
    if args.json:
        check_output_file(args.json, "--json")  # before the minutes of measuring
    settings = BenchSettings.tiny_settings() if args.tiny else BenchSettings.quick_settings() if args.quick else BenchSettings()
    settings.threads = args.threads
    from ..learners.config import check_device

    try:
        check_device(args.device)
    except ValueError as exc:
        raise UserError(f"--{exc}") from None
    settings.device = args.device
    figures, payload = run_bench(settings, only, log=lambda line: print(line, flush=True))
    print()
    print(format_table(figures, markdown=args.markdown))
    if args.json:
        path = write_json_atomic(args.json, payload)
        print(f"wrote {path}")
    return 0
