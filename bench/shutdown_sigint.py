"""Ctrl-C to the recorder, many times, with a core kept busy beside it: crashes and bags.

Each run starts a passive recorder of /notes on a private DDS domain, publishes numbered
messages until its bag holds some, then a burst (pending in the writer), and sends SIGINT;
every third run a second SIGINT follows into the close. A run is whole when the recorder
exits 0 and its bag opens with rosbags and holds exactly the count the recorder said it
wrote, in increasing order (DDS may drop some of a burst before the recorder takes them:
a KEEP_LAST reader; what it took is what is checked). Before the signal-thread
fix (pusher_common.shutdown) about one run in ten ended with SIGSEGV (-11).

  .venv/bin/python bench/shutdown_sigint.py --runs 200 --json bench/shutdown_sigint.json
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

from offline_rl_core.common.machine import cpu_model_and_flags
from offline_rl_core.pipelines.processes import RosProcess, isolated_ros_env
from ros2_shim.ament_index import ros2_run


def sent_numbers(bag: Path) -> list[int]:
    from rosbags.rosbag2 import Reader

    from offline_rl_core.data.bag import typestore

    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == "/notes"]
        return [int(typestore().deserialize_cdr(raw, "std_msgs/msg/String").data)
                for _, _, raw in reader.messages(conns)]


def recording(proc, bag: Path, pub, String, timeout: float = 60.0) -> None:
    """Publish numbered messages until the recorder has flushed some into its bag."""
    deadline = time.monotonic() + timeout
    i = 0
    while time.monotonic() < deadline:
        if "subscribed to /notes" in proc.output():
            pub.publish(String(data=str(i)))
            i += 1
            try:
                if sent_numbers(bag):
                    return
            except Exception:  # noqa: BLE001 - nothing flushed yet
                pass
        time.sleep(0.02)
    raise RuntimeError(f"the recorder recorded nothing in {timeout:.0f} s:\n{proc.output()[-2000:]}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=200)
    parser.add_argument("--burst", type=int, default=2000, help="messages published just before each SIGINT")
    parser.add_argument("--json", default="bench/shutdown_sigint.json")
    args = parser.parse_args()

    import os

    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import String

    env = isolated_ros_env()
    os.environ["ROS_DOMAIN_ID"] = env["ROS_DOMAIN_ID"]
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = env["ROS_AUTOMATIC_DISCOVERY_RANGE"]
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("sigint_bench", context=context)
    pub = node.create_publisher(String, "/notes", QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    tmp = Path(tempfile.mkdtemp(prefix="sigint-bench-"))
    outcomes, failures, messages = Counter(), [], []
    started = time.monotonic()
    try:
        for run in range(args.runs):
            bag = tmp / f"run{run}.db3"
            proc = RosProcess(ros2_run("recorder", "node", "--passive", "--topics", "notes", "--out", bag), env,
                              tmp / f"run{run}.log", name="recorder").start()
            try:
                recording(proc, bag, pub, String)
                for i in range(args.burst):
                    pub.publish(String(data=str(10**6 + i)))
                proc.proc.send_signal(signal.SIGINT)
                if run % 3 == 2:
                    time.sleep(0.002 * (run % 7))
                    proc.proc.send_signal(signal.SIGINT)
                rc = proc.wait(60)
            finally:
                proc.stop()
            wrote = re.search(r"(\d+) messages\)", proc.output())
            try:
                numbers = sent_numbers(bag)
                whole = (wrote is not None and len(numbers) == int(wrote[1]) > 0
                         and all(a < b for a, b in zip(numbers, numbers[1:])))
            except Exception as exc:  # noqa: BLE001 - an unreadable bag is the outcome measured
                numbers, whole = [], False
                failures.append({"run": run, "error": str(exc)[:200]})
            outcome = "whole" if rc == 0 and whole else f"exit {rc}" if rc != 0 else "bag not whole"
            outcomes[outcome] += 1
            messages.append(len(numbers))
            if outcome != "whole":
                failures.append({"run": run, "outcome": outcome, "log": proc.output()[-1500:]})
            shutil.rmtree(bag, ignore_errors=True) if bag.is_dir() else bag.unlink(missing_ok=True)
            print(f"run {run + 1}/{args.runs}: {outcome} ({len(numbers)} messages)", file=sys.stderr, flush=True)
    finally:
        busy.kill()
        busy.wait()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    model, flags = cpu_model_and_flags()
    result = {
        "command": " ".join([".venv/bin/python", *sys.argv]),
        "cpu": {"model": model, "flags": sorted(f for f in flags if f in ("avx2", "avx512f", "avx512_bf16",
                                                                              "amx_tile"))},
        "cores": os.cpu_count(), "runs": args.runs, "burst": args.burst, "second_sigint_every": 3,
        "busy_core": True, "outcomes": dict(outcomes), "crashes": sum(v for k, v in outcomes.items()
                                                                      if k.startswith("exit")),
        "messages_per_bag": {"min": min(messages), "max": max(messages)},
        "wall_s": round(time.monotonic() - started, 1), "failures": failures[:10],
    }
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: result[k] for k in ("outcomes", "crashes", "wall_s")}), file=sys.stderr)
    shutil.rmtree(tmp, ignore_errors=True)
    return 0 if result["crashes"] == 0 and outcomes["whole"] == args.runs else 1


if __name__ == "__main__":
    sys.exit(main())
