"""Proposal for offline_rl_core/data/bag/reader.py (not used by the runtime): read /pusher/transition
in chunks of 65,536 rows straight into the Transitions columns, instead of a list of every payload.
It prints its time and peak memory; with `check`, whether its output equals read_transitions'
array for array.

Run: python bench/proposals/stream_reader.py BAG.db3 [check]
"""
import numpy as np, time, resource, sys, itertools
from pathlib import Path
from offline_rl_core.data.bag import open_bag, decode_transition_payloads
from offline_rl_core.data.bag.reader import sqlite_storages
from offline_rl_core.data.transitions import Transitions, TRANSITION_LAYOUT, LAYOUT_SLICES

CHUNK = 65536
INT_FIELDS = ("episode", "step", "source"); BOOL_FIELDS = ("terminated", "truncated", "success")

def read_streaming(path):
    with open_bag(path) as reader:
        conns = [c for c in reader.connections if c.topic == "/pusher/transition"]
        n = sum(c.msgcount for c in conns)
        out = {}
        for label, size in TRANSITION_LAYOUT:
            dt = np.int64 if label in INT_FIELDS else bool if label in BOOL_FIELDS else np.float32
            out[label] = np.empty((n, size) if label in ("obs", "action", "next_obs") else (n,), dt)
        pos = 0
        for storage in sqlite_storages(reader):
            ids = [c.id for c in storage.connections if c.topic == "/pusher/transition"]
            cur = storage.dbconn.execute(f"SELECT data FROM messages WHERE topic_id IN ({','.join('?'*len(ids))}) ORDER BY timestamp, id", ids)
            while True:
                chunk = list(itertools.islice(cur, CHUNK))
                if not chunk: break
                rows = decode_transition_payloads([r[0] for r in chunk])
                k = len(rows)
                for label, size in TRANSITION_LAYOUT:
                    col = rows[:, LAYOUT_SLICES[label]]
                    if out[label].ndim == 1:
                        col = col[:, 0]
                        out[label][pos:pos+k] = (col != 0) if out[label].dtype == bool else col
                    else:
                        out[label][pos:pos+k] = col
                pos += k
    return Transitions(**out)

if __name__ == "__main__":
    import offline_rl_core.learners.loop
    def rss():
        for line in open("/proc/self/status"):
            if line.startswith("VmRSS:"): return int(line.split()[1])//1024
    base = rss()
    t = time.perf_counter(); d = read_streaming(sys.argv[1]); dt = time.perf_counter() - t
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024
    nbytes = sum(a.nbytes for a in d.__dict__.values())
    print(f"streaming: {len(d)} rows in {dt:.2f}s, peak +{peak-base} MiB, arrays {nbytes/2**20:.0f} MiB")
    if len(sys.argv) > 2:
        from offline_rl_core.data.bag import read_transitions
        ref = read_transitions(sys.argv[1])
        print("equal to read_transitions:", all(np.array_equal(getattr(ref, k), getattr(d, k)) for k in d.__dict__))
