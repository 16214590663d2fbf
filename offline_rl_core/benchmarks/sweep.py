"""Sweep figures: a 12-run `offline-rl sweep` on Ray against the same runs in local worker
processes (the sweep's local engine, `offline-rl experiment`'s workers).

Rounds alternate: the sweep on local workers with no Ray running, then Ray started, the
same sweep on it, Ray stopped. "Ray on a running cluster" is the sweep's wall time once Ray
is up (what `ray start --head` and `--address auto` give); "Ray with its start" adds the
start of a private Ray (`--engine ray` without `--address`). Every engine must write the
same metrics.json for every run; the bench checks it.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

from ..common.machine import available_cores
from ..runs.local_engine import LocalEngine
from ..runs.sweep import load_sweep_spec, run_sweep
from .harness import BenchSettings, figure, median, pending

REPO = Path(__file__).resolve().parents[2]
LEARNERS = ("bc", "awac", "iql")


def spec_text(s: BenchSettings, bag: Path) -> str:
    seeds = list(range(s.sweep_runs // len(LEARNERS)))
    return (f"name: bench\nbags: {bag}\nseeds: {seeds}\nvariants: [{', '.join('{algo: %s}' % a for a in LEARNERS)}]\n"
            f"train: {{steps: {s.sweep_steps}, hidden: {s.hidden}, batch_size: {s.batch_size}}}\n"
            f"eval: {{episodes: {s.sweep_eval_episodes}}}\nbaseline: bc\n")


def _cpu_s_of_this_and_waited_children() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _cpu_s_of_descendants() -> float:
    """CPU seconds of this process's live descendants (Ray's GCS, raylet and workers, and
    the children each has reaped), read from /proc before they are stopped."""
    parents, times = {}, {}
    tick = os.sysconf("SC_CLK_TCK")
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        parents[int(entry)] = int(fields[1])
        times[int(entry)] = sum(int(x) for x in fields[11:15]) / tick  # utime stime cutime cstime
    me, total = os.getpid(), 0.0
    for pid in times:
        p = parents.get(pid)
        while p not in (None, 0, 1, me):
            p = parents.get(p)
        if p == me and pid != me:
            total += times[pid]
    return total


def run(s: BenchSettings, log=print) -> list:
    from ..runs.ray_engine import RayEngine, connected, ray_missing

    if ray_missing():
        return [pending("sweep", f"sweep_{s.sweep_runs}_runs_wall_s_ray", "s", "local worker processes",
                        ray_missing(), status="skipped")]
    cores = available_cores()
    times: dict[str, list[float]] = {"local": [], "ray_running": [], "ray_start": [], "local_cpu_s": [],
                                     "ray_cpu_s": []}
    with tempfile.TemporaryDirectory(prefix="bench_sweep_") as tmp:
        tmp = Path(tmp)
        bag = REPO / "bags" / "mix.db3"
        if s.tiny:  # a small bag of its own: seconds, not minutes
            from ..data.bag import write_transitions
            from ..data.collect import collect_transitions

            bag = tmp / "tiny.db3"
            write_transitions(bag, collect_transitions(s.episodes, 0.3, 0))
        spec_path = tmp / "bench.yaml"
        spec_path.write_text(spec_text(s, bag))
        spec = load_sweep_spec(spec_path)
        quiet = lambda line: None  # noqa: E731
        for r in range(max(1, s.sweep_repeats)):
            t0, c0 = time.perf_counter(), _cpu_s_of_this_and_waited_children()
            run_sweep(spec, tmp / f"local{r}", LocalEngine(cores), log=quiet)
            times["local"].append(time.perf_counter() - t0)
            times["local_cpu_s"].append(_cpu_s_of_this_and_waited_children() - c0)
            t0 = time.perf_counter()
            with connected(None):
                t1 = time.perf_counter()
                c1 = _cpu_s_of_this_and_waited_children() + _cpu_s_of_descendants()
                run_sweep(spec, tmp / f"ray{r}", RayEngine(log=quiet), log=quiet)
                t2 = time.perf_counter()
                times["ray_cpu_s"].append(_cpu_s_of_this_and_waited_children() + _cpu_s_of_descendants() - c1)
            times["ray_running"].append(t2 - t1)
            times["ray_start"].append(time.perf_counter() - t0)
            log(f"  round {r}: local {times['local'][-1]:.1f}s ({times['local_cpu_s'][-1]:.1f} CPU s), ray "
                f"{times['ray_running'][-1]:.1f}s ({times['ray_cpu_s'][-1]:.1f} CPU s; "
                f"{times['ray_start'][-1]:.1f}s with its start and stop)")
            for run in spec.runs:
                a = (tmp / f"local{r}" / run.name / "metrics.json").read_bytes()
                b = (tmp / f"ray{r}" / run.name / "metrics.json").read_bytes()
                if a != b:
                    raise AssertionError(f"{run.name}: the Ray run's metrics.json differs from the local run's")
    med = {k: median(v) for k, v in times.items()}
    note = (f"{len(spec.runs)} runs ({', '.join(LEARNERS)} x {len(spec.runs) // len(LEARNERS)} seeds) of "
            f"{s.sweep_steps} steps, hidden {s.hidden}, {s.sweep_eval_episodes} eval rollouts each, on bags/mix.db3; "
            f"local: {cores} worker processes; Ray: {cores} CPUs, one per run; median of {len(times['local'])} "
            "alternating rounds; every run's metrics.json is the same bytes on both")
    extra = {k: [round(x, 2) for x in v] for k, v in times.items()}
    return [
        figure("sweep", f"sweep_{len(spec.runs)}_runs_wall_s_ray_running", "s", med["ray_running"], med["local"],
               "the same runs in local worker processes", higher_is_better=False,
               target=lambda o, r, x: o <= 1.05 * r, target_text="<= 1.05x the local wall time (5 % overhead)",
               note=note + "; Ray already running", extra=extra),
        figure("sweep", f"sweep_{len(spec.runs)}_runs_wall_s_ray_with_start", "s", med["ray_start"], med["local"],
               "the same runs in local worker processes", higher_is_better=False,
               target_text="(info: includes starting and stopping a private Ray)", note=note, extra=extra),
        # on a machine shared with other jobs the wall time is their load as much as ours:
        # the CPU seconds every process of each engine used say what the engine itself costs
        figure("sweep", f"sweep_{len(spec.runs)}_runs_cpu_s_ray_running", "CPU s", med["ray_cpu_s"], med["local_cpu_s"],
               "the same runs in local worker processes", higher_is_better=False,
               target=lambda o, r, x: o <= 1.05 * r, target_text="<= 1.05x (info: CPU, not wall, time)",
               note="user + system CPU seconds of the driver, Ray's GCS, raylet and workers (local: the parent "
                    "and its workers) over the sweep, Ray already running", extra=extra),
    ]
