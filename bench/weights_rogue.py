"""The policy node under a rogue on learner/weights: is every state still answered in its period?

One policy node (the chapter's 256-wide network, acting on the session learner's signed
weights) gets states at 50 Hz from a probe in this process, first alone (the reference),
then with a rogue publishing on learner/weights at the same rate, alternately: a
well-formed message from the project's own encoder signed with another key (version 2**62,
a saturating bias) and the review's 2 KB torch file whose layer is a stride-0 view of
8192x8192. Per phase: answer latency (state published -> action received, this process's
clock), the share answered within the 20 ms period, the node's RSS, and what it refused.

  .venv/bin/python bench/weights_rogue.py --json bench/weights_rogue.json
"""

from __future__ import annotations

import argparse
import array
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from fuzz_messages import stride0_checkpoint  # noqa: E402
from offline_rl_core.benchmarks.harness import machine_info, utc_now  # noqa: E402
from offline_rl_core.common.machine import cpu_model_and_flags  # noqa: E402
from offline_rl_core.pipelines.processes import RosProcess, isolated_ros_env  # noqa: E402
from offline_rl_core.serving.checkpoint import save_checkpoint  # noqa: E402
from offline_rl_core.serving.policy import policy_sequential  # noqa: E402
from offline_rl_core.serving.signing import Signer, load_signer, make_session_keys  # noqa: E402
from offline_rl_core.serving.weights import encode_weights  # noqa: E402
from ros2_shim.ament_index import ros2_run  # noqa: E402

PERIOD_S = 0.02
START = 1_800_000_000 * 10**9


def checkpoint(seed: int, version: int | None, hidden: int = 256) -> dict:
    import torch

    torch.manual_seed(seed)
    net = policy_sequential(8, hidden, 2)
    ckpt = {"format": "pusher-rl/policy", "version": 1, "algorithm": "sac", "obs_dim": 8, "act_dim": 2,
            "hidden": hidden, "policy_state": {k: v.detach().clone() for k, v in net.state_dict().items()}}
    if version is not None:
        ckpt["weights_version"] = version
    return ckpt


def rss_mib(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        return int(next(line for line in f if line.startswith("VmRSS:")).split()[1]) / 1024


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="per phase")
    parser.add_argument("--rogue-hz", type=float, nargs="+", default=[1.0, 50.0],
                        help="rates of the rogue's messages, one phase each (1 Hz: as often as the learner "
                             "publishes; 50 Hz: a flood, one per state)")
    parser.add_argument("--json", default="bench/weights_rogue.json")
    args = parser.parse_args()

    import rclpy
    from geometry_msgs.msg import PointStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import JointState
    from std_msgs.msg import MultiArrayDimension, String, UInt8MultiArray

    tmp = Path(tempfile.mkdtemp(prefix="rogue-bench-"))
    keys = make_session_keys(tmp / "keys")
    learner = load_signer(keys.signing_key)
    served = save_checkpoint(tmp / "policy.pt", checkpoint(0, None))
    rogue = checkpoint(3, 2**62)
    rogue["policy_state"]["4.bias"][:] = 1e6
    messages = {"v1": encode_weights(checkpoint(1, 1), learner), "rogue": encode_weights(rogue, Signer.generate()),
                "stride-0": stride0_checkpoint(8192)}
    env = isolated_ros_env()
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        os.environ[key] = env[key]
    proc = RosProcess(ros2_run("policy", "node", "--ros-args", "-p", f"checkpoint:={served}",
                               "-p", "weights_topic:=learner/weights", "-p", f"weights_key:={keys.public_key}"),
                      env, tmp / "policy.log", name="policy").start()
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("rogue_bench", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    pubs = {t: node.create_publisher(m, f"/{t}", 10) for t, m in (
        ("pusher/target", PointStamped), ("pusher/fingertip", PointStamped), ("pusher/state", JointState))}
    weights = node.create_publisher(UInt8MultiArray, "/learner/weights", QoSProfile(
        depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    received: dict[int, tuple[float, int]] = {}
    versions: dict[int, int] = {}
    statuses: list[dict] = []
    node.create_subscription(JointState, "/policy/action", lambda m: received.setdefault(
        m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, (time.monotonic(), 0)), 1000)
    node.create_subscription(String, "/policy/provenance", lambda m: versions.setdefault(
        json.loads(m.data)["stamp"], json.loads(m.data)["weights_version"]), 1000)
    node.create_subscription(String, "/policy/status", lambda m: statuses.append(json.loads(m.data)), 10)
    rng = np.random.default_rng(0)
    stamp = [START]
    sent: dict[int, float] = {}

    def spin_until(predicate, timeout):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not predicate():
            executor.spin_once(timeout_sec=0.005)
        return predicate()

    def send_state() -> int:
        stamp[0] += 20_000_000
        s = stamp[0]
        sec, nsec = divmod(s, 10**9)
        for topic in ("pusher/target", "pusher/fingertip"):
            msg = PointStamped()
            msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nsec
            msg.point.x, msg.point.y = (float(v) for v in rng.uniform(-0.2, 0.2, 2))
            pubs[topic].publish(msg)
        msg = JointState(name=["shoulder", "elbow"], position=list(rng.uniform(-1, 1, 2)),
                         velocity=list(rng.uniform(-1, 1, 2)))
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nsec
        sent[s] = time.monotonic()
        pubs["pusher/state"].publish(msg)
        return s

    built = {}
    for name, data in messages.items():  # made once: the probe's own cost stays out of the figures
        built[name] = UInt8MultiArray(data=array.array("B", data))
        built[name].layout.dim = [MultiArrayDimension(label="pusher-rl/weights", size=len(data), stride=1)]

    def send_weights(name: str) -> None:
        weights.publish(built[name])

    def phase(rogue_hz: float) -> dict:
        first = stamp[0] + 20_000_000
        rss = [rss_mib(proc.pid)]
        t0 = time.monotonic()
        k = 0
        while time.monotonic() - t0 < args.seconds:
            tick = t0 + k * PERIOD_S
            spin_until(lambda: time.monotonic() >= tick, 1.0)
            send_state()
            every = round(1 / (rogue_hz * PERIOD_S)) if rogue_hz else 0
            if every and k % every == 0:
                send_weights("rogue" if (k // every) % 2 else "stride-0")
            k += 1
            if k % 50 == 0:
                rss.append(rss_mib(proc.pid))
        spin_until(lambda: all(s in received for s in sent if s >= first), 2.0)
        stamps = [s for s in sent if s >= first]
        latency = np.array([received[s][0] - sent[s] for s in stamps if s in received]) * 1000
        return {"rogue_hz": rogue_hz, "states": len(stamps), "answered": int(latency.size),
                "within_period": float(np.mean(latency <= PERIOD_S * 1000)) if latency.size else 0.0,
                "latency_ms": {"p50": round(float(np.percentile(latency, 50)), 3),
                               "p99": round(float(np.percentile(latency, 99)), 3),
                               "max": round(float(latency.max()), 3)},
                "rss_mib": {"start": round(rss[0], 1), "max": round(max(rss), 1)},
                "weights_versions_acting": sorted({versions[s] for s in stamps if s in versions})}

    try:
        assert spin_until(lambda: weights.get_subscription_count() > 0 and node.count_publishers("/policy/action"),
                          60), proc.output()
        while not spin_until(lambda: bool(received), 1.0):
            send_state()
        send_weights("v1")
        while True:
            s = send_state()
            if spin_until(lambda: s in versions, 2.0) and versions[s] == 1:
                break
        reference = phase(0.0)
        under_rogue = [phase(hz) for hz in args.rogue_hz]
        spin_until(lambda: False, 1.5)  # the status after the last refusal
        refused = statuses[-1]["rejected"] if statuses else {}
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
        proc.stop()
    model, flags = cpu_model_and_flags()
    result = {
        "command": " ".join([".venv/bin/python", *sys.argv]),
        "machine": machine_info(), "measured_at": utc_now(), "loadavg_end": list(os.getloadavg()),
        "cpu": {"model": model, "flags": sorted(f for f in flags if f in ("avx2", "avx512f", "avx512_bf16",
                                                                              "amx_tile"))},
        "cores": os.cpu_count(), "period_ms": PERIOD_S * 1000, "seconds_per_phase": args.seconds,
        "rogue_messages": {name: len(data) for name, data in messages.items() if name != "v1"},
        "reference": reference, "under_rogue": under_rogue, "refused": refused,
        "ratio_p99": [round(p["latency_ms"]["p99"] / reference["latency_ms"]["p99"], 3) for p in under_rogue],
        "rss_growth_mib": round(max(p["rss_mib"]["max"] for p in under_rogue) - reference["rss_mib"]["start"], 1),
    }
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
