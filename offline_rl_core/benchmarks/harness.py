"""The benchmark harness: settings, figures, interleaved timing, the table and the JSON.

A figure is one measured quantity of ours next to its reference, taken in the same
process run. Timings on a shared machine drift, so ``interleave`` alternates the
contenders (A B A B ...) and keeps the median of each, and every figure is reported
as a ratio to its reference, never as a bare time.
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import statistics
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

from ..learners.config import TrainConfig

GROUPS = ("train", "decode", "eval", "serve", "record", "online", "sweep", "fleet")


@dataclass
class BenchSettings:
    """How long each figure runs. ``quick()`` fits in under 3 minutes on 2 cores."""

    quick: bool = False
    # training throughput: gradient steps per timed run, and interleaved repeats
    train_steps: int = 1000
    train_repeats: int = 3
    hidden: int = TrainConfig.hidden
    batch_size: int = TrainConfig.batch_size
    episodes: int = 200  # the chapter's dataset
    # `offline-rl experiment --seeds 0 1 2` against three chapter runs
    experiment_seeds: tuple[int, ...] = (0, 1, 2)
    experiment_steps: int = TrainConfig.steps
    experiment_eval: tuple[int, int] = (5, 20)  # suites x episodes per arm and seed (the chapter's)
    # bag decoding
    decode_repeats: int = 5
    large_bag_rows: int = 2_000_000
    large_bag_train_steps: int = 200
    # evaluation rollouts
    eval_episodes: int = 100
    eval_repeats: int = 3
    # serving
    inference_calls: int = 10_000
    dds_messages: int = 10_000
    dds_rate_hz: float = 100.0
    # recording
    record_episodes: int = 200
    realtime_seconds: float = 60.0
    # `offline-rl sweep` on Ray against local worker processes: a 12-run sweep, alternating rounds
    sweep_runs: int = 12
    sweep_steps: int = 3000
    sweep_eval_episodes: int = 20
    sweep_repeats: int = 2
    # fleets of bags: bags of 20,000 transitions (bags/mix.db3), decoded in fresh processes
    fleet_bag_counts: tuple[int, ...] = (1, 10, 100)
    fleet_repeats: int = 3
    threads: int | None = None  # torch intra-op threads; None = auto (see ``choose_threads``)
    device: str = "cpu"  # where the training figures train: cpu, or cuda / cuda:N
    tiny: bool = False  # test settings: seconds, not minutes; figures meaningless

    @classmethod
    def quick_settings(cls) -> "BenchSettings":
        return cls(quick=True, train_steps=150, train_repeats=2, experiment_steps=300, decode_repeats=3,
                   large_bag_rows=400_000, large_bag_train_steps=50, eval_repeats=2, inference_calls=5000,
                   dds_messages=1500, record_episodes=20, realtime_seconds=10.0, sweep_steps=500, sweep_repeats=1,
                   sweep_eval_episodes=10, fleet_repeats=2)

    @classmethod
    def tiny_settings(cls) -> "BenchSettings":
        """For tests: every code path, tiny sizes."""
        return cls(quick=True, tiny=True, train_steps=3, train_repeats=1, hidden=16, batch_size=16, episodes=4,
                   experiment_seeds=(0, 1), experiment_steps=3, experiment_eval=(1, 2), decode_repeats=1, large_bag_rows=2000,
                   large_bag_train_steps=2, eval_episodes=4, eval_repeats=1, inference_calls=50, dds_messages=20,
                   dds_rate_hz=200.0, record_episodes=1, realtime_seconds=1.0, sweep_runs=3, sweep_steps=3,
                   sweep_eval_episodes=1, sweep_repeats=1, fleet_bag_counts=(1, 3), fleet_repeats=1)


@dataclass
class Figure:
    """One benchmark row.

    ``ratio`` is always "times better than the reference": ours/ref for rates
    (higher is better), ref/ours for times and latencies. ``target`` is a predicate
    over (ours, reference, ratio) with its text; ``met`` is None when not decided.
    """

    group: str
    name: str
    unit: str
    ours: float | None
    reference: float | None
    reference_name: str
    higher_is_better: bool = True
    target_text: str = ""
    met: bool | None = None
    status: str = "ok"  # ok | pending | skipped
    note: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def ratio(self) -> float | None:
        if self.ours is None or self.reference is None or self.ours == 0 or self.reference == 0:
            return None
        return self.ours / self.reference if self.higher_is_better else self.reference / self.ours

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("group")
        d.pop("name")
        d["ratio"] = None if self.ratio is None else round(self.ratio, 3)
        for k in ("ours", "reference"):
            if isinstance(d[k], float):
                d[k] = round(d[k], 6)
        return d


def figure(group: str, name: str, unit: str, ours, reference, reference_name: str, *, higher_is_better=True,
           target: Callable[[float, float, float], bool] | None = None, target_text: str = "", note: str = "",
           extra: dict | None = None) -> Figure:
    fig = Figure(group, name, unit, None if ours is None else float(ours),
                 None if reference is None else float(reference), reference_name, higher_is_better, target_text,
                 note=note, extra=extra or {})
    if target is not None and fig.ours is not None and (fig.reference is not None or fig.ratio is None):
        try:
            fig.met = bool(target(fig.ours, fig.reference, fig.ratio))
        except TypeError:
            fig.met = None
    return fig


def pending(group: str, name: str, unit: str, reference_name: str, reason: str, target_text: str = "",
            status: str = "pending") -> Figure:
    return Figure(group, name, unit, None, None, reference_name, target_text=target_text, status=status, note=reason)


def interleave(contenders: dict[str, Callable[[], float]], repeats: int) -> dict[str, list[float]]:
    """Call each contender in turn, ``repeats`` rounds (A B C A B C ...); each call
    returns its own measurement (a rate or a time). Lists of measurements per name."""
    out: dict[str, list[float]] = {k: [] for k in contenders}
    for _ in range(max(1, repeats)):
        for name, fn in contenders.items():
            out[name].append(float(fn()))
    return out


def median(values: list[float]) -> float:
    return float(statistics.median(values))


def timed(fn: Callable[[], object]) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def percentile(values, q: float) -> float:
    import numpy as np

    return float(np.percentile(np.asarray(values, dtype=np.float64), q))


# ----------------------------------------------------------------------------- machine

def machine_info() -> dict:
    import numpy as np
    import torch

    from ..common import machine
    from ..fast import kernel_choice

    model = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    load = os.getloadavg() if hasattr(os, "getloadavg") else (None, None, None)
    return {
        "cpu_model": model,
        "cpu_count": os.cpu_count(),
        "isa_flags": machine.isa_flags(),  # as the kernels may use them
        "cpu_isa_flags": [f for f in machine.ISA_FLAGS if f in machine.cpu_model_and_flags()[1]],
        "kernel_isa_limits": machine.isa_limits(),
        "kernels": kernel_choice.report(),
        "amx": "amx_bf16" in machine.isa_flags(),
        "avx512_bf16": "avx512_bf16" in machine.isa_flags(),
        "native_bf16": kernel_choice.native_bf16(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "numpy": np.__version__,
        "python": platform.python_version(),
        "cuda_available": bool(torch.cuda.is_available()),
        "loadavg_start": [round(x, 2) for x in load] if load[0] is not None else None,
        "gpu": "not measured (no GPU lent to this run)" if not torch.cuda.is_available() else torch.cuda.get_device_name(0),
    }


def invoked_command() -> str:
    """The command line this process runs, as a user types it: ``offline-rl ...`` for the
    CLI (also when re-run under ``python -m``), ``python SCRIPT ...`` for a bench script."""
    argv = sys.argv or [""]
    script = Path(argv[0])
    if script.name == "offline-rl" or script.parts[-2:] in (("offline_rl_core", "__main__.py"), ("commands", "cli.py")):
        return shlex.join(["offline-rl", *argv[1:]])
    try:  # a script path relative to the directory it was run from, as it was typed
        script = script.resolve().relative_to(Path.cwd())
    except ValueError:
        pass
    return shlex.join(["python", str(script), *argv[1:]])


def utc_now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def run_facts() -> dict:
    """What every JSON file under bench/ says about its figures: the command that measured
    them, the machine and when (bench/results_page.py prints them beside the figures)."""
    return {"command": invoked_command(), "machine": machine_info(), "measured_at": utc_now()}


def add_run_facts(store: dict) -> None:
    """``run_facts`` for a JSON file that several commands fill in turn (a resumable bench
    script): this command joins its ``commands``, ``measured_at`` becomes now, and the file
    keeps one machine (figures from another CPU belong in another file)."""
    facts = run_facts()
    stored = store.setdefault("machine", facts["machine"])
    if _cpu(stored) != _cpu(facts["machine"]):
        raise SystemExit(f"this file holds figures measured on {_cpu(stored)}, not on this CPU "
                         f"({_cpu(facts['machine'])}): write them to another --json")
    commands = store.setdefault("commands", [])
    if facts["command"] not in commands:
        commands.append(facts["command"])
    store["measured_at"] = facts["measured_at"]


def _cpu(m: dict) -> str:
    """A machine record's CPU model and flags, under the keys the writers of the time used."""
    flags = m.get("cpu_isa_flags") or m.get("isa_flags") or m.get("isa") or []
    return " ".join([m.get("cpu_model") or m.get("cpu") or "an unrecorded CPU", *flags])


def choose_threads(requested: int | None) -> tuple[int, str]:
    """torch's default threads for the run's references, and why: torch's own default
    (as a user runs the chapter's script or d3rlpy), unless ``--threads`` says otherwise.
    The training figures time the references with one thread too and keep the faster;
    ours runs as ``offline-rl train`` does by default (or on ``--threads``)."""
    import torch

    if requested:
        return requested, f"--threads {requested}"
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0
    return torch.get_num_threads(), f"torch default {torch.get_num_threads()} (load {load:.2f})"


# ----------------------------------------------------------------------------- output

def _fmt(x: float | None, unit: str) -> str:
    if x is None:
        return "-"
    if unit in ("ms", "s") or abs(x) < 10:
        return f"{x:.3g}" if abs(x) < 1000 else f"{x:,.0f}"
    return f"{x:,.0f}"


def format_table(figures: list[Figure], markdown: bool = False) -> str:
    head = ["group", "figure", "ours", "reference", "ref", "ratio", "target", "met"]
    rows = []
    for f in figures:
        met = {True: "yes", False: "NO", None: "-"}[f.met]
        if f.status != "ok":
            met = f.status
        rows.append([
            f.group, f.name, f"{_fmt(f.ours, f.unit)} {f.unit}" if f.ours is not None else "-",
            f"{_fmt(f.reference, f.unit)} {f.unit}" if f.reference is not None else "-", f.reference_name,
            "-" if f.ratio is None else f"{f.ratio:.2f}x", f.target_text, met,
        ])
    if markdown:
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines)
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    fmt = lambda r: "  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip()  # noqa: E731
    return "\n".join([fmt(head), fmt(["-" * w for w in widths])] + [fmt(r) for r in rows])


def results_json(figures: list[Figure], settings: BenchSettings, machine: dict, wall_s: float) -> dict:
    out: dict = {g: {} for g in GROUPS}
    for f in figures:
        out.setdefault(f.group, {})[f.name] = f.to_dict()
    out["machine"] = machine
    out["settings"] = asdict(settings)
    out["wall_s"] = round(wall_s, 2)
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    out["machine"]["loadavg_end"] = [round(x, 2) for x in load] if load else None
    return out


def run_bench(settings: BenchSettings, only: list[str] | None = None, log: Callable[[str], None] = print) -> tuple[list[Figure], dict]:
    """Run the selected figure groups; returns the figures and the JSON payload."""
    import importlib

    import torch

    threads, why = choose_threads(settings.threads)
    torch.set_num_threads(threads)
    groups = list(only) if only else list(GROUPS)
    unknown = [g for g in groups if g not in GROUPS]
    if unknown:
        raise ValueError(f"unknown bench group(s) {', '.join(unknown)}; expected some of {', '.join(GROUPS)}")
    started = utc_now()
    machine = machine_info()
    machine["threads_choice"] = why
    log(f"bench on {machine['cpu_model']} ({machine['cpu_count']} cpus, torch threads {why}, "
        f"ISA {' '.join(machine['isa_flags']) or 'none'}"
        + (f" (kernels capped by {' '.join(f'{k}={v}' for k, v in machine['kernel_isa_limits'].items())}"
           f" on a CPU with {' '.join(machine['cpu_isa_flags'])})" if machine["kernel_isa_limits"] else "")
        + f", load {machine['loadavg_start']})")
    modules = {"train": "train", "decode": "decode", "eval": "eval_rollouts", "serve": "serve", "record": "record",
               "online": "online", "sweep": "sweep", "fleet": "fleet"}
    t0 = time.perf_counter()
    figures: list[Figure] = []
    for g in groups:
        t1 = time.perf_counter()
        log(f"[{g}] ...")
        module = importlib.import_module(f"offline_rl_core.benchmarks.{modules[g]}")
        try:
            got = module.run(settings, log)
        except Exception as exc:  # a broken group must not hide the others' figures
            got = [pending(g, "error", "", "", f"{type(exc).__name__}: {exc}", status="skipped")]
        figures.extend(got)
        log(f"[{g}] {time.perf_counter() - t1:.1f}s")
    payload = results_json(figures, settings, machine, time.perf_counter() - t0)
    payload["command"], payload["measured_at"] = invoked_command(), started
    return figures, payload


def figures_from_json(payload: dict) -> list[Figure]:
    """The figures of a results JSON, e.g. to re-render its table (``python -m
    offline_rl_core.benchmarks.harness results.json``)."""
    figs = []
    for g in GROUPS:
        for name, d in payload.get(g, {}).items():
            figs.append(Figure(g, name, d["unit"], d["ours"], d["reference"], d["reference_name"], d["higher_is_better"],
                               d["target_text"], d["met"], d["status"], d["note"], d.get("extra", {})))
    return figs


if __name__ == "__main__":
    for arg in sys.argv[1:]:
        print(format_table(figures_from_json(json.loads(Path(arg).read_text())), markdown=True))
