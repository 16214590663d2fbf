"""Bag decoding figures: ``read_transitions`` against rosbags' own per-message
``deserialize_cdr`` (sqlite3 and MCAP), an MCAP file without summary against the same
messages with one, and a 2,000,000-transition bag (decode time, training memory).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..data.bag import TRANSITION_TOPIC, decode_transition_payloads, read_transitions, write_transitions
from ..data.bag.writer import typestore
from ..data.collect import collect_transitions
from ..data.transitions import TRANSITION_WIDTH, Transitions
from .harness import BenchSettings, figure, interleave, median, pending


def rosbags_rows(path: Path) -> np.ndarray:
    """The reference: rosbags' Reader and one ``deserialize_cdr`` per message."""
    from rosbags.rosbag2 import Reader

    store = typestore()
    with Reader(path) as reader:
        conns = [c for c in reader.connections if c.topic == TRANSITION_TOPIC]
        n = sum(c.msgcount for c in conns)
        rows = np.empty((n, TRANSITION_WIDTH), np.float32)
        for i, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
            rows[i] = store.deserialize_cdr(raw, conn.msgtype).data
    return rows


def tiled_transitions(base: Transitions, rows: int) -> Transitions:
    """``rows`` transitions: copies of ``base`` with fresh episode ids."""
    reps = -(-rows // len(base))
    out = base.to_rows()
    big = np.tile(out, (reps, 1))[:rows]
    ep_col = 8 + 2 + 1 + 8 + 3  # the episode column of the layout
    n_ep = int(base.episode.max()) + 1
    big[:, ep_col] += np.repeat(np.arange(reps, dtype=np.float32) * n_ep, len(base))[:rows]
    return Transitions.from_rows(big)


_MEMORY_PROBE = r"""
import json, sys, time
import numpy as np, torch
from offline_rl_core.data.bag import read_transitions
from offline_rl_core.learners import TrainConfig, train_seeds
path, steps, hidden, batch = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
import offline_rl_core.learners.loop  # everything imported (and the step replayer loaded) before the baseline
from offline_rl_core.fast import graph_runner  # the speed layer, registered onto the learners as a run has it
graph_runner.unavailable_reason()
def status_kib(key):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1])
base = status_kib("VmRSS")
t0 = time.perf_counter()
data = read_transitions(path)
decode_s = time.perf_counter() - t0
arrays = sum(getattr(data, k).nbytes for k in ("obs", "action", "reward", "next_obs", "terminated", "truncated", "success", "episode", "step", "source"))
train_seeds(data, TrainConfig(algo="awac", steps=steps, hidden=hidden, batch_size=batch, log_every=steps), [0])
# VmHWM, not ru_maxrss: after fork + exec, ru_maxrss still counts the parent's memory
# at the fork (Linux keeps the old mm's high-water mark), VmHWM is this process's own.
peak = status_kib("VmHWM")
print(json.dumps({"decode_s": decode_s, "arrays_bytes": arrays, "peak_delta_bytes": (peak - base) * 1024, "rows": len(data)}))
"""


def run(s: BenchSettings, log=print) -> list:
    figs = []
    data = collect_transitions(s.episodes, 0.3, 0)
    with tempfile.TemporaryDirectory(prefix="bench_decode_") as tmp:
        bag = Path(tmp) / "mix.db3"
        write_transitions(bag, data)
        n = len(data)
        from ..data.bag import open_bag, topic_payloads

        with open_bag(bag) as reader:
            payloads = topic_payloads(reader, TRANSITION_TOPIC)
        store = typestore()
        msgtype = "std_msgs/msg/Float32MultiArray"

        def ours_file():
            t0 = time.perf_counter()
            read_transitions(bag)
            return n / (time.perf_counter() - t0)

        def ref_file():
            t0 = time.perf_counter()
            rosbags_rows(bag)
            return n / (time.perf_counter() - t0)

        def ours_mem():
            t0 = time.perf_counter()
            decode_transition_payloads(payloads)
            return n / (time.perf_counter() - t0)

        def ref_mem():
            t0 = time.perf_counter()
            rows = np.empty((n, TRANSITION_WIDTH), np.float32)
            for i, p in enumerate(payloads):
                rows[i] = store.deserialize_cdr(p, msgtype).data
            return n / (time.perf_counter() - t0)

        assert np.array_equal(read_transitions(bag).to_rows(), rosbags_rows(bag)), "decoders disagree"
        rates = {k: median(v) for k, v in interleave(
            {"ours_file": ours_file, "ref_file": ref_file, "ours_mem": ours_mem, "ref_mem": ref_mem},
            s.decode_repeats).items()}
        log("  decode transitions/s: " + ", ".join(f"{k} {v:,.0f}" for k, v in rates.items()))
        figs.append(figure("decode", "bag_decode_transitions_per_s", "transitions/s", rates["ours_file"], rates["ref_file"],
                           "rosbags Reader + deserialize_cdr per message",
                           target=lambda o, r, x: o >= 1e6 and x >= 5.0, target_text=">= 1,000,000/s and >= 5x",
                           note=f"read_transitions on a {n}-transition .db3, from the file (SQL fetch included)"))
        figs.append(figure("decode", "payload_decode_transitions_per_s", "transitions/s", rates["ours_mem"], rates["ref_mem"],
                           "rosbags deserialize_cdr per message", target=lambda o, r, x: o >= 1e6 and x >= 5.0,
                           target_text=">= 1,000,000/s and >= 5x", note="CDR payloads already in memory"))
        figs.extend(mcap_figures(s, data, Path(tmp), log))
        figs.extend(large_bag_figures(s, data, Path(tmp), log))
    return figs


def copy_as_mcap(source: Path, target: Path, **layout) -> None:
    """A bag's messages rewritten by Foxglove's ``mcap`` writer (profile ros2) with the
    layout options given (its defaults otherwise: chunked, zstd, a full summary)."""
    from mcap.writer import Writer
    from rosbags.rosbag2 import Reader

    store = typestore()
    with Reader(source) as reader, target.open("wb") as f:
        writer = Writer(f, **layout)
        writer.start(profile="ros2", library="offline_rl_core bench")
        channels = {}
        for conn in reader.connections:
            msgdef = store.generate_msgdef(conn.msgtype, ros_version=2)[0]
            schema = writer.register_schema(conn.msgtype, "ros2msg", msgdef.encode())
            channels[conn.id] = writer.register_channel(conn.topic, "cdr", schema, {"offered_qos_profiles": ""})
        for conn, stamp, raw in reader.messages():
            writer.add_message(channels[conn.id], log_time=stamp, data=raw, publish_time=stamp)
        writer.finish()


def mcap_figures(s: BenchSettings, data: Transitions, tmp: Path, log=print) -> list:
    """read_transitions on MCAP: the default layout (a full summary, as rosbag2, rosbags and
    the recorder write it) against rosbags' per-message reading; and a file without summary,
    whose data section is scanned at open, against the same messages with a full summary."""
    n = len(data)
    default = tmp / "mix.mcap"
    write_transitions(default, data)

    def rate(fn, path):
        def measure():
            t0 = time.perf_counter()
            fn(path)
            return n / (time.perf_counter() - t0)
        return measure

    contenders = {"ours": rate(read_transitions, default), "ref": rate(rosbags_rows, default)}
    try:
        from mcap.writer import IndexType
    except ImportError:
        full = bare = None
    else:
        full, bare = tmp / "full.mcap", tmp / "no_summary.mcap"
        copy_as_mcap(default, full)
        copy_as_mcap(default, bare, use_statistics=False, use_summary_offsets=False, repeat_channels=False,
                     repeat_schemas=False, index_types=IndexType.NONE)
        for path in (full, bare):
            assert np.array_equal(read_transitions(path).to_rows(), data.to_rows()), f"{path.name} reads other rows"
        contenders |= {"full": rate(read_transitions, full), "bare": rate(read_transitions, bare)}
    rates = {k: median(v) for k, v in interleave(contenders, s.decode_repeats).items()}
    log("  MCAP decode transitions/s: " + ", ".join(f"{k} {v:,.0f}" for k, v in rates.items()))
    figs = [figure("decode", "mcap_bag_decode_transitions_per_s", "transitions/s", rates["ours"], rates["ref"],
                   "rosbags Reader + deserialize_cdr per message", target=lambda o, r, x: x >= 1.0,
                   target_text=">= 1x", note=f"read_transitions on a {n}-transition .mcap (a full summary)")]
    if bare is None:
        figs.append(pending("decode", "mcap_no_summary_decode_transitions_per_s", "transitions/s",
                            "the same messages with a full summary", "needs the mcap package (the dev extra)"))
    else:
        figs.append(figure("decode", "mcap_no_summary_decode_transitions_per_s", "transitions/s", rates["bare"],
                           rates["full"], "read_transitions, the same file with a full summary",
                           target=lambda o, r, x: x >= 0.5, target_text=">= 0.5x",
                           note="Foxglove's mcap writer, no summary: the data section is scanned at open"))
    return figs


def large_bag_figures(s: BenchSettings, base: Transitions, tmp: Path, log=print) -> list:
    rows = s.large_bag_rows
    bag = tmp / "large.db3"
    t0 = time.perf_counter()
    write_transitions(bag, tiled_transitions(base, rows))
    log(f"  wrote a {rows:,}-transition bag in {time.perf_counter() - t0:.1f}s ({bag.stat().st_size / 2**20:.0f} MiB)")
    env = dict(os.environ)
    proc = subprocess.run([sys.executable, "-c", _MEMORY_PROBE, str(bag), str(s.large_bag_train_steps), str(s.hidden),
                           str(s.batch_size)], capture_output=True, text=True, env=env, timeout=600)
    if proc.returncode != 0:
        raise RuntimeError(f"large-bag probe failed: {proc.stderr.strip()[-400:]}")
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    log(f"  large bag: decode {got['decode_s']:.2f}s, peak +{got['peak_delta_bytes'] / 2**20:.0f} MiB over "
        f"{got['arrays_bytes'] / 2**20:.0f} MiB of arrays")
    label = f"{rows / 1e6:g}M"
    # the 4 s target is for 2M transitions; a smaller (quick) bag is held to the same rate
    limit_s = 4.0 * rows / 2_000_000
    # ...but not to the memory ratio: torch's fixed ~100 MiB of first-step buffers is small
    # beside 2M rows' arrays and not beside a quick run's
    full = rows >= 2_000_000
    return [
        figure("decode", f"large_bag_{label}_decode_s", "s", got["decode_s"], limit_s, f"target {limit_s:.2g} s",
               higher_is_better=False, target=lambda o, r, x: o < r, target_text=f"< {limit_s:.2g} s",
               note=f"read_transitions, fresh process; {rows:,} transitions"),
        figure("decode", f"large_bag_{label}_train_peak_mem", "MiB", got["peak_delta_bytes"] / 2**20,
               got["arrays_bytes"] / 2**20, "its arrays (Transitions nbytes)", higher_is_better=False,
               target=(lambda o, r, x: o < 2 * r) if full else None,
               target_text="< 2x arrays" if full else "(info: the target is for 2M rows)",
               note=f"peak RSS growth over decode + {s.large_bag_train_steps} AWAC steps"),
    ]
