"""Recording figures over DDS: lockstep recording throughput (sim + recorder nodes) and
the realtime sim's 50 Hz timing.

References: recording is held against ``offline-rl collect``'s in-process rate (the
same episodes without DDS) and the 1,000 transitions/s target; the realtime sim
against its ideal 20 ms grid.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from ..task.pusher_reach import CONTROL_HZ, MAX_STEPS
from .harness import BenchSettings, figure, pending
from .ros_procs import bench_node, isolate, ros2_command, ros_missing, run_probe


def lockstep_figures(s: BenchSettings, tmp: Path, log=print) -> list:
    from ..data.bag import read_transitions
    from ..data.collect import collect_transitions

    ros2 = ros2_command()
    episodes = s.record_episodes
    out = tmp / "rec.db3"
    t0 = time.perf_counter()
    with bench_node([ros2, "run", "sim", "node", "--ros-args", "-p", "mode:=lockstep", "-p", "seed:=0"],
                     tmp / "sim_lockstep.log") as sim:
        with bench_node([ros2, "run", "recorder", "node", "--out", str(out), "--episodes", str(episodes),
                          "--expert-frac", "0.3", "--seed", "0"], tmp / "recorder.log") as rec:
            rc = rec.wait(timeout=max(60.0, episodes * MAX_STEPS / 200.0))
            if rc is None:
                raise RuntimeError(f"recorder did not finish {episodes} episodes; log: {rec.output()[-600:]}")
            if rc != 0:
                raise RuntimeError(f"recorder exit {rc}; log: {rec.output()[-600:]}")
        wall = time.perf_counter() - t0
        if sim.proc.poll() is not None and sim.proc.returncode not in (0, None):
            log(f"  sim exited {sim.proc.returncode}: {sim.output()[-300:]}")
    rows = len(read_transitions(out))
    steady = _steady_rate(out)
    t1 = time.perf_counter()
    collect_transitions(episodes, 0.3, 0)
    in_process = episodes * MAX_STEPS / (time.perf_counter() - t1)
    rate = rows / wall
    log(f"  lockstep recording: {rows} transitions in {wall:.1f}s = {rate:,.0f}/s, steady {steady}/s "
        f"(in-process collect {in_process:,.0f}/s)")
    return [figure("record", f"lockstep_recording_transitions_per_s_{episodes}ep", "transitions/s", rate, in_process,
                   "offline-rl collect in-process (no DDS)", target=lambda o, r, x: o >= 1000.0,
                   target_text=">= 1,000/s (20,000 steps < 20 s)",
                   note=f"{rows} transitions in {wall:.1f} s wall, node start-up and discovery included; "
                        f"steady rate {steady}/s",
                   extra={"wall_s": round(wall, 3), "transitions": rows, "steady_transitions_per_s": steady})]


def _steady_rate(bag: Path) -> float | None:
    """Transitions/s between the first and last recorded transition (receive stamps):
    the rate once the nodes have started and discovered each other."""
    from rosbags.rosbag2 import Reader

    from ..data.bag import TRANSITION_TOPIC

    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == TRANSITION_TOPIC]
        stamps = [t for _, t, _ in reader.messages(connections=conns)]
    if len(stamps) < 2 or stamps[-1] == stamps[0]:
        return None
    return round((len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1e9), 1)


def realtime_figures(s: BenchSettings, tmp: Path, log=print) -> list:
    """Subscribe to /pusher/state of a realtime sim and read its tick stamps."""
    ros2 = ros2_command()
    seconds = s.realtime_seconds
    period_ms = 1000.0 / CONTROL_HZ
    with bench_node([ros2, "run", "sim", "node", "--ros-args", "-p", "mode:=realtime", "-p", "seed:=0"],
                     tmp / "sim_realtime.log") as sim:
        try:
            stamps = run_probe(["realtime-stamps", seconds], timeout=seconds + 90)
        except RuntimeError as exc:
            raise RuntimeError(f"{exc}; sim log: {sim.output()[-600:]}") from exc
    st = np.array(stamps, dtype=np.int64)
    if st.size < 3:
        raise RuntimeError("too few states received from the realtime sim")
    gaps = np.diff(st) / 1e6
    missed = int(np.clip(np.floor(gaps / period_ms + 0.5) - 1, 0, None).sum())
    grid = st[0] + np.arange(st.size) * period_ms * 1e6  # where each tick should be, no drift allowed
    # ticks lost by the subscriber show up as missed; lateness is measured on what arrived
    lateness_ms = (st - grid) / 1e6
    late = int((np.abs(gaps - period_ms) > period_ms).sum())
    expected = int(round(seconds * CONTROL_HZ))
    log(f"  realtime {seconds:g}s: {st.size} states (expected ~{expected}), period mean {gaps.mean():.3f} ms, "
        f"std {gaps.std():.3f}, max {gaps.max():.3f} ms, missed {missed}, late {late}")
    return [figure("record", f"realtime_50hz_{seconds:g}s_missed_or_late", "steps", missed + late, 0,
                   "ideal 50 Hz grid", higher_is_better=False, target=lambda o, r, x: o == 0,
                   target_text="0 beyond one period",
                   note=f"{st.size} ticks; period mean {gaps.mean():.3f} ms, std {gaps.std():.3f}, max {gaps.max():.3f} ms; "
                        f"drift from the grid at the end {lateness_ms[-1]:+.2f} ms",
                   extra={"ticks": int(st.size), "missed": missed, "late": late, "max_gap_ms": round(float(gaps.max()), 3),
                          "std_ms": round(float(gaps.std()), 4)})]


def run(s: BenchSettings, log=print) -> list:
    why = ros_missing()
    names = [f"lockstep_recording_transitions_per_s_{s.record_episodes}ep", f"realtime_50hz_{s.realtime_seconds:g}s_missed_or_late"]
    if why:
        return [pending("record", n, "", "", why) for n in names]
    isolate()
    figs = []
    with tempfile.TemporaryDirectory(prefix="bench_record_") as tmp:
        for name, fn in zip(names, (lockstep_figures, realtime_figures)):
            try:
                figs.extend(fn(s, Path(tmp), log))
            except Exception as exc:
                figs.append(pending("record", name, "", "", f"failed: {type(exc).__name__}: {exc}"[:500], status="skipped"))
    return figs
