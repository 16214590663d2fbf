"""Crash safety of recording: faults x storages x kill moments, transitions received vs
recoverable.

For each fault (SIGKILL, SIGTERM, SIGINT), storage (.db3, .mcap) and kill moment, a sim
and a recorder node run on a private DDS domain; the recorder gets the signal that many
seconds after it starts recording. A probe subscriber in this process sees every
/pusher/transition the sim publishes; "received" counts those that arrived before the
signal, from the first one the bag holds (the recorder's subscription may match a
little after the probe's), with any the bag holds beyond them. Then:
- "read": transitions `read_transitions` gets from the bag as the kill left it (no repair);
- "rosbags": whether rosbags' own Reader opens it as left;
- "repaired": transitions after `offline-rl bag repair` (when the bag needed it).
The recorded rows are checked against the probe's (same transitions, in order).

  flock /tmp/pusher-cpu.lock .venv/bin/python bench/crash_safety.py --json bench/crash_safety.json

Modes: `active` (lockstep sim driven by the recorder) and `passive` (realtime sim at 50 Hz,
recorder --passive). The JSON holds every trial with the command and the machine; the table
it prints is bench/RESULTS.md's "Crash safety of recording" (`results_page.crash_table`).
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

from offline_rl_core.benchmarks.harness import run_facts
from offline_rl_core.common.atomic import write_json_atomic
from offline_rl_core.common.errors import UserError
from offline_rl_core.data.bag import read_transitions, repair_bag
from offline_rl_core.data.transitions import LAYOUT_SLICES
from offline_rl_core.pipelines.processes import RosProcess, isolated_ros_env
from results_page import crash_table
from ros2_shim.ament_index import ros2_run

FAULTS = {"SIGKILL": signal.SIGKILL, "SIGTERM": signal.SIGTERM, "SIGINT": signal.SIGINT}
STORAGES = {"sqlite3": ".db3", "mcap": ".mcap"}
EPISODE, STEP = LAYOUT_SLICES["episode"].start, LAYOUT_SLICES["step"].start


class Probe:
    """Counts /pusher/transition messages on the bench's domain, in a spinning thread."""

    def __init__(self):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions
        from std_msgs.msg import Float32MultiArray

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("crash_safety_probe", context=self.context)
        self.lock = threading.Lock()
        self.seen: list[tuple[int, int]] = []
        self.arrival: list[float] = []
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(Float32MultiArray, "/pusher/transition", self.on_transition, qos)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.spin, daemon=True)
        self.running = True
        self.thread.start()

    def on_transition(self, msg) -> None:
        with self.lock:
            self.seen.append((int(msg.data[EPISODE]), int(msg.data[STEP])))
            self.arrival.append(time.monotonic())

    def spin(self) -> None:
        while self.running:
            self.executor.spin_once(timeout_sec=0.05)

    def take(self, before: float = float("inf")) -> list[tuple[int, int]]:
        """The transitions seen (that arrived before ``before``), and forget all."""
        with self.lock:
            out = [k for k, t in zip(self.seen, self.arrival) if t < before]
            self.seen, self.arrival = [], []
        return out

    def close(self) -> None:
        self.running = False
        self.thread.join()
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)


def rows_key(transitions) -> list[tuple[int, int]]:
    return list(zip(transitions.episode.astype(int).tolist(), transitions.step.astype(int).tolist()))


def count(path: Path) -> tuple[int | None, list[tuple[int, int]], str]:
    """(transitions read, their keys, problem) of a bag as it is on disk."""
    try:
        transitions = read_transitions(path)
    except UserError as exc:
        return None, [], str(exc)
    return len(transitions), rows_key(transitions), ""


def rosbags_opens(path: Path) -> bool:
    from rosbags.rosbag2 import Reader

    try:
        with Reader(path) as reader:
            return reader.message_count >= 0
    except Exception:
        return False


def trial(mode: str, fault: str, storage: str, delay: float, probe: Probe, env: dict, work: Path, seed: int) -> dict:
    bag = work / f"rec{STORAGES[storage]}"
    logs = work / "logs"
    if mode == "active":
        sim_args = ["--ros-args", "-p", "mode:=lockstep", "-p", f"seed:={seed}", "-p", "wait_for_subscribers:=2"]
        rec_args = ["--out", bag, "--episodes", 1000, "--expert-frac", 0.5, "--seed", seed]
    else:
        sim_args = ["--ros-args", "-p", f"seed:={seed}"]
        rec_args = ["--out", bag, "--passive"]
    probe.take()
    with RosProcess(ros2_run("sim", "node", *sim_args), env, logs / "sim.log") as sim, \
            RosProcess(ros2_run("recorder", "node", *rec_args), env, logs / "recorder.log") as recorder:
        if not recorder.wait_for_output("recording", timeout=60):
            raise RuntimeError(f"the recorder did not start: {recorder.output()[-2000:]}")
        deadline = time.monotonic() + 30
        while not probe.seen and time.monotonic() < deadline:  # transitions flow (the probe has matched)
            time.sleep(0.02)
        started = time.monotonic()
        time.sleep(delay)
        killed = time.monotonic()
        os.kill(recorder.pid, FAULTS[fault])
        recorder.wait(timeout=30)
        time.sleep(0.3)  # the probe drains what was in flight
        sim.stop()
    seen = probe.take(before=killed)  # published before the signal
    n_read, keys, problem = count(bag)
    opens = rosbags_opens(bag)
    repaired_n, repair_steps = n_read, []
    if n_read is None or (storage == "sqlite3" and Path(f"{bag}-wal").exists()):
        try:
            repair_steps = repair_bag(bag)
            repaired_n, keys, problem2 = count(bag)
            problem = problem or problem2
        except UserError as exc:
            repaired_n, problem = None, f"{problem}; repair: {exc}"
    # Received: what the probe saw from the bag's first transition on, and the bag itself
    # (either subscription may have matched the sim a little before the other).
    start = min(keys) if keys else (min(seen) if seen else (0, 0))
    seen_after = [k for k in seen if k >= start]
    received = len(set(seen_after) | set(keys))
    lost = len(set(seen_after) - set(keys))
    # The bag must be a gap-free prefix of what was published from its first transition on.
    in_order = keys == seen_after[: len(keys)]
    result = {
        "mode": mode, "fault": fault, "storage": storage, "delay_s": delay, "received": received,
        "read": n_read, "rosbags_opens": opens, "repaired": repaired_n, "repair_steps": repair_steps,
        "gap_free_prefix": in_order, "lost": lost, "rate_per_s": len(seen) / max(killed - started, 1e-9),
        "problem": problem,
    }
    shutil.rmtree(work)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--modes", nargs="+", default=["active", "passive"], choices=["active", "passive"])
    parser.add_argument("--faults", nargs="+", default=list(FAULTS), choices=list(FAULTS))
    parser.add_argument("--storages", nargs="+", default=list(STORAGES), choices=list(STORAGES))
    parser.add_argument("--moments", type=int, default=10, help="kill moments per cell (default 10)")
    parser.add_argument("--first", type=float, default=1.0, help="first kill moment, s after recording starts")
    parser.add_argument("--step", type=float, default=0.37, help="between kill moments, s (not a multiple of the flush interval)")
    parser.add_argument("--json", type=Path, help="write every trial here")
    args = parser.parse_args()
    facts = run_facts()
    env = isolated_ros_env()
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")})
    probe = Probe()
    results = []
    try:
        for mode in args.modes:
            for fault in args.faults:
                for storage in args.storages:
                    for k in range(args.moments):
                        delay = round(args.first + k * args.step, 3)
                        work = Path(tempfile.mkdtemp(prefix="crash_safety."))
                        r = trial(mode, fault, storage, delay, probe, env, work, seed=k)
                        results.append(r)
                        print(f"{mode:7s} {fault:7s} {storage:7s} kill at {delay:5.2f} s: received {r['received']:5d}, "
                              f"read {r['read']}, rosbags {'opens' if r['rosbags_opens'] else 'refuses'}, "
                              f"repaired {r['repaired']}, lost {r['lost']}, gap-free prefix {r['gap_free_prefix']}"
                              + (f" [{r['problem']}]" if r["problem"] else ""), flush=True)
    finally:
        probe.close()
    print(crash_table(results))
    if args.json:
        write_json_atomic(args.json, {"trials": results, **facts})
    return 0


if __name__ == "__main__":
    sys.exit(main())
