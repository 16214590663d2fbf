"""SIGKILL the policy node driving the realtime sim: how long until the sim's torque is zero?

The sim (realtime, pusher_reach, torques taken on effort_controller/commands as an effort
controller takes them) is driven by the policy node (a random 64-wide network: nonzero
torques). Each round starts a policy node, waits until five states in a row show its
torque applied, kills it with SIGKILL and measures, on this process's clock, the time
from the kill to the first ``pusher/state`` whose effort (the torque the actuators applied)
is zero: the sim's watchdog (three control periods by default) plus up to one tick and the
state's way to the probe. Also in sim time: ticks between the last state before the kill
and the first zero-torque one.

  .venv/bin/python bench/watchdog_latency.py --rounds 10 --json bench/watchdog_latency.json
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from offline_rl_core.benchmarks.harness import machine_info, utc_now
from offline_rl_core.common.machine import cpu_model_and_flags
from offline_rl_core.pipelines.processes import RosProcess, isolated_ros_env
from offline_rl_core.serving.checkpoint import save_checkpoint
from offline_rl_core.serving.policy import policy_sequential
from offline_rl_core.task.spec import load_task


def checkpoint(seed: int, hidden: int = 64) -> dict:
    import torch

    torch.manual_seed(seed)
    net = policy_sequential(8, hidden, 2)
    return {"format": "pusher-rl/policy", "version": 1, "algorithm": "sac", "obs_dim": 8, "act_dim": 2,
            "hidden": hidden, "policy_state": {k: v.detach().clone() for k, v in net.state_dict().items()}}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--json", default="bench/watchdog_latency.json")
    args = parser.parse_args()

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import JointState

    task = load_task("pusher_reach")
    tmp = Path(tempfile.mkdtemp(prefix="watchdog-bench-"))
    served = save_checkpoint(tmp / "policy.pt", checkpoint(0))
    env = isolated_ros_env()
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        os.environ[key] = env[key]
    sim = RosProcess([sys.executable, "-m", "pusher_sim.node", "--ros-args", "-p",
                      "effort_topic:=effort_controller/commands"], env, tmp / "sim.log", name="sim").start()
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("watchdog_bench", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    states: list[tuple[float, int, bool]] = []  # (received, stamp ns, torque applied)
    node.create_subscription(JointState, "/pusher/state", lambda m: states.append(
        (time.monotonic(), m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, any(m.effort))), 100)

    def spin_until(predicate, timeout):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not predicate():
            executor.spin_once(timeout_sec=0.002)
        return predicate()

    latencies_ms, ticks = [], []
    try:
        for k in range(args.rounds):
            policy = RosProcess([sys.executable, "-m", "pusher_policy.node", "--ros-args", "-p",
                                 f"checkpoint:={served}"], env, tmp / f"policy{k}.log", name="policy").start()
            start = len(states)
            if not spin_until(lambda: len(states) - start >= 5 and all(s[2] for s in states[-5:]), 60):
                raise RuntimeError(f"the policy never drove the sim:\n{policy.output()[-2000:]}")
            last_before = states[-1][1]
            killed = time.monotonic()
            os.kill(policy.pid, signal.SIGKILL)
            at = len(states)
            if not spin_until(lambda: any(not s[2] for s in states[at:]), 10):
                raise RuntimeError(f"the torque never went to zero:\n{sim.output()[-2000:]}")
            zero = next(s for s in states[at:] if not s[2])
            latencies_ms.append((zero[0] - killed) * 1000)
            ticks.append(round((zero[1] - last_before) / (task.control_period * 1e9)))
            policy.stop()
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        sim.stop()
    lat = np.array(latencies_ms)
    model, flags = cpu_model_and_flags()
    result = {
        "command": " ".join([".venv/bin/python", *sys.argv]),
        "machine": machine_info(), "measured_at": utc_now(),  # for bench/results_page.py
        "cpu": {"model": model, "flags": sorted(f for f in flags if f in ("avx2", "avx512f", "avx512_bf16",
                                                                              "amx_tile"))},
        "cores": os.cpu_count(), "period_ms": task.control_period * 1000,
        "command_timeout_ms": round(task.command_timeout * 1000, 3), "rounds": args.rounds,
        "kill_to_zero_torque_ms": {"p50": round(float(np.median(lat)), 3), "max": round(float(lat.max()), 3),
                                   "all": [round(float(v), 3) for v in lat]},
        "within_100ms": float(np.mean(lat <= 100.0)),
        "ticks_from_last_driven_state_to_zero_torque": ticks,
    }
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
