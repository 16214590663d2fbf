"""Fleet figures: decoding 1, 10 and 100 bags of 20,000 transitions (``data/fleet.py``) against
reading them one after another in one process and concatenating (what `offline-rl train`
did before fleets), and the peak memory of each as the number of bags grows.

Each contender runs in a fresh process, so that its peak (VmHWM) is its own: ``read_fleet``
(worker processes where the bags pay for them), the same bags streamed through
``iter_fleet`` (each bag taken and dropped: what a reader that writes or summarises a fleet
holds), the reference, and, where Ray is installed, ``read_fleet`` with Ray tasks on a
private 2-CPU Ray. Memory is the peak growth of the reading process over its state before
the read; a worker process's own peak is in ``extra``.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .harness import BenchSettings, figure, median, pending

REPO = Path(__file__).resolve().parents[2]
MODES = ("serial", "local", "stream", "ray")

_PROBE = "import sys; from offline_rl_core.benchmarks.fleet import probe; probe(*sys.argv[1:])"


def _status_kib(key: str, pid: str = "self") -> int:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    return 0


def probe(mode: str, paths_file: str, repeats: str) -> None:
    """One contender in this (fresh) process; prints its JSON line."""
    from dataclasses import fields

    import numpy as np  # noqa: F401 - loaded before the baseline, as everything the read uses

    from ..common.machine import available_cores
    from ..data import bag as _bag  # noqa: F401
    from ..data.bag import read_transitions
    from ..data.fleet import auto_workers, iter_fleet, local_executor, read_fleet
    from ..data.transitions import Transitions

    paths = json.loads(Path(paths_file).read_text())
    workers = auto_workers(paths) if mode == "local" else min(available_cores(), len(paths))
    context = None
    if mode == "ray":
        from ..runs.ray_engine import connected, read_fleet_on_ray

        context = connected(None, num_cpus=2)
        context.__enter__()
    base = _status_kib("VmRSS")
    seconds, rows, arrays, worker_peaks = [], 0, 0, []
    for _ in range(int(repeats)):
        t0 = time.perf_counter()
        if mode == "serial":
            parts, offset = [], 0
            for p in paths:
                data = read_transitions(p)
                data.episode = data.episode - data.episode.min() + offset
                offset = int(data.episode.max()) + 1
                parts.append(data)
            data = parts[0] if len(parts) == 1 else Transitions.concatenate(parts)
            del parts
        elif mode == "local":
            with local_executor(workers) as pool:
                data, _ = read_fleet(paths, executor=pool, ahead=2 * workers)
                for proc in getattr(pool, "_processes", {}).values():
                    worker_peaks.append(_status_kib("VmHWM", str(proc.pid)) * 1024)
        elif mode == "stream":
            data, n, held = None, 0, 0
            with local_executor(workers) as pool:
                for part, _ in iter_fleet(paths, pool, ahead=2 * workers):
                    n += len(part)
                    held += sum(getattr(part, f.name).nbytes for f in fields(Transitions))
                for proc in getattr(pool, "_processes", {}).values():
                    worker_peaks.append(_status_kib("VmHWM", str(proc.pid)) * 1024)
        else:
            data, _ = read_fleet_on_ray(paths, ahead=4)
        seconds.append(time.perf_counter() - t0)
        if data is not None:
            rows = len(data)
            arrays = sum(getattr(data, f.name).nbytes for f in fields(Transitions))
        else:
            rows, arrays = n, held
        del data
    peak = _status_kib("VmHWM")
    if context is not None:
        context.__exit__(None, None, None)
    print(json.dumps({"seconds": seconds, "rows": rows, "arrays_bytes": arrays, "workers": workers,
                      "peak_growth_bytes": (peak - base) * 1024, "worker_peak_bytes": max(worker_peaks, default=0)}))


def _run_probe(mode: str, paths: list[str], repeats: int, tmp: Path) -> dict:
    listing = tmp / f"paths_{len(paths)}.json"
    listing.write_text(json.dumps(paths))
    proc = subprocess.run([sys.executable, "-c", _PROBE, mode, str(listing), str(repeats)], capture_output=True,
                          text=True, timeout=1200)
    if proc.returncode != 0:
        raise RuntimeError(f"fleet probe {mode} failed: {proc.stderr.strip()[-400:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run(s: BenchSettings, log=print) -> list:
    from ..runs.ray_engine import ray_missing

    no_ray = ray_missing()  # not imported here: the probes start Ray in processes of their own
    modes = MODES if no_ray is None else MODES[:-1]
    figs = []
    with tempfile.TemporaryDirectory(prefix="bench_fleet_") as tmp:
        tmp = Path(tmp)
        bag = REPO / "bags" / "mix.db3"
        if s.tiny:
            from ..data.bag import write_transitions
            from ..data.collect import collect_transitions

            bag = tmp / "tiny.db3"
            write_transitions(bag, collect_transitions(s.episodes, 0.3, 0))
        counts = list(s.fleet_bag_counts)
        for i in range(max(counts)):  # a fleet's day: the same 20k-transition bag from every arm
            shutil.copyfile(bag, tmp / f"arm{i:03d}.db3")
        got: dict[tuple[str, int], dict] = {}
        for n in counts:
            paths = [str(tmp / f"arm{i:03d}.db3") for i in range(n)]
            for mode in modes:
                got[mode, n] = r = _run_probe(mode, paths, s.fleet_repeats, tmp)
                log(f"  {n:>3} bags, {mode:>6}: {r['rows'] / median(r['seconds']):,.0f} transitions/s, peak +"
                    f"{r['peak_growth_bytes'] / 2**20:.0f} MiB (arrays {r['arrays_bytes'] / 2**20:.0f} MiB, "
                    f"{r['workers']} workers)")
    mib = 2**20
    rows_per_bag = got["serial", counts[0]]["rows"] // counts[0]
    for n in counts:
        serial, local, stream = got["serial", n], got["local", n], got["stream", n]
        rate = lambda r: r["rows"] / median(r["seconds"])  # noqa: E731
        over = lambda r: (r["peak_growth_bytes"] - r["arrays_bytes"]) / mib  # noqa: E731
        note = f"{n} bags of {rows_per_bag:,} transitions (.db3), {local['workers']} decode worker(s)"
        figs.append(figure("fleet", f"fleet_{n}_bags_transitions_per_s", "transitions/s", rate(local), rate(serial),
                           "the bags read one after another in one process", note=note,
                           extra={"seconds": local["seconds"], "reference_seconds": serial["seconds"]}))
        figs.append(figure("fleet", f"fleet_{n}_bags_peak_over_arrays_MiB", "MiB", max(over(local), 0.01),
                           max(over(serial), 0.01), "the reference's peak over the same arrays",
                           higher_is_better=False, note=note + "; the reading process's peak growth less the "
                           "merged arrays", extra={"arrays_MiB": round(local["arrays_bytes"] / mib, 1),
                                                   "worker_peak_MiB": round(local["worker_peak_bytes"] / mib, 1)}))
        figs.append(figure("fleet", f"fleet_{n}_bags_stream_peak_MiB", "MiB", max(stream["peak_growth_bytes"] / mib, 0.01),
                           stream["arrays_bytes"] / mib, "the fleet's arrays (what holding it all takes)",
                           higher_is_better=False, note=note + "; iter_fleet, each bag taken and dropped",
                           extra={"worker_peak_MiB": round(stream["worker_peak_bytes"] / mib, 1)}))
        if no_ray is None:
            ray = got["ray", n]
            figs.append(figure("fleet", f"fleet_{n}_bags_ray_transitions_per_s", "transitions/s", rate(ray),
                               rate(serial), "the bags read one after another in one process",
                               note=f"{n} bags; Ray tasks on a private 2-CPU Ray (started before the clock), "
                                    "copied out of the object store into one allocation",
                               extra={"peak_over_arrays_MiB": round(over(ray), 1)}))
        else:
            figs.append(pending("fleet", f"fleet_{n}_bags_ray_transitions_per_s", "transitions/s", "serial", no_ray,
                                status="skipped"))
    lo, hi = counts[0], counts[-1]
    flat_over = lambda m: (got[m, hi]["peak_growth_bytes"] - got[m, hi]["arrays_bytes"]) / mib  # noqa: E731
    figs.append(figure("fleet", f"fleet_peak_over_arrays_{hi}_vs_{lo}_bags_MiB", "MiB",
                       max(flat_over("local"), 0.01),
                       max((got["local", lo]["peak_growth_bytes"] - got["local", lo]["arrays_bytes"]) / mib, 0.01),
                       f"the same at {lo} bag(s)", higher_is_better=False,
                       target=lambda o, r, x: o <= r + 32, target_text=f"flat: within 32 MiB of the {lo}-bag figure",
                       note="read_fleet: memory beyond the merged arrays as the fleet grows"))
    figs.append(figure("fleet", f"fleet_stream_peak_{hi}_vs_{lo}_bags_MiB", "MiB",
                       max(got["stream", hi]["peak_growth_bytes"] / mib, 0.01),
                       max(got["stream", lo]["peak_growth_bytes"] / mib, 0.01), f"the same at {lo} bag(s)",
                       higher_is_better=False, target=lambda o, r, x: o <= r + 32,
                       target_text=f"flat: within 32 MiB of the {lo}-bag figure",
                       note="iter_fleet: peak growth of the reading process as the fleet grows"))
    return figs
