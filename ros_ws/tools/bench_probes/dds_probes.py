"""DDS probes for `offline-rl bench`, run as their own processes.

They are the only benchmark code that imports rclpy, which is why they live here and
not in offline_rl_core (which has no ROS import). `offline_rl_core.benchmarks` starts
them with the bench's isolated ROS_DOMAIN_ID and reads one JSON line from stdout.

    python dds_probes.py echo                    # a bare echo node: /pusher/state -> /policy/action
    python dds_probes.py round-trip N RATE_HZ    # time N states answered on /policy/action
    python dds_probes.py realtime-stamps SECONDS # stamps of /pusher/state from a realtime sim
    python dds_probes.py online-actor SECONDS    # states, the policy node's answers and weights arrivals
"""

import json
import sys
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PointStamped
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState

from offline_rl_core.benchmarks.harness import percentile
from offline_rl_core.benchmarks.ros_procs import wait_until
from offline_rl_core.task.pusher_reach import JOINT_NAMES


def round_trip(n: int, rate_hz: float) -> dict:
    """Publish target + state at ``rate_hz``; time each /policy/action answering a stamp."""

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("bench_driver", context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    sent: dict[int, float] = {}
    received: dict[int, float] = {}

    def on_action(msg):
        key = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if key in sent and key not in received:
            received[key] = time.perf_counter()

    state_pub = node.create_publisher(JointState, "/pusher/state", 10)
    target_pub = node.create_publisher(PointStamped, "/pusher/target", 10)
    node.create_subscription(JointState, "/policy/action", on_action, 10)
    spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731
    state = JointState(name=list(JOINT_NAMES), position=[0.3, -0.4], velocity=[0.0, 0.1], effort=[0.0, 0.0])
    target = PointStamped()
    target.header.frame_id = "world"
    target.point.x, target.point.y = 0.1, 0.05
    base_ns = 1_000 * 1_000_000_000  # s: the warm-up's keys below it stay positive stamps

    def send(k: int) -> int:
        key = base_ns + k * 10_000_000
        stamp = state.header.stamp
        stamp.sec, stamp.nanosec = divmod(key, 1_000_000_000)
        target.header.stamp = stamp
        target_pub.publish(target)
        sent[key] = time.perf_counter()
        state_pub.publish(state)
        return key

    try:
        ok = wait_until(lambda: state_pub.get_subscription_count() > 0 and node.count_publishers("/policy/action") > 0,
                        30.0, spin)
        if not ok:
            raise RuntimeError("the node under test never matched /pusher/state and /policy/action")
        # warm-up until answers flow (discovery of the reverse path may lag)
        k = 0
        wait_until(lambda: len(received) > 0, 15.0, lambda t: (send(-1000 - k), spin(t)))
        for _ in range(50):
            key = send(-500 + _)
            wait_until(lambda: key in received, 0.5, spin, 0.001)
        sent.clear()
        received.clear()
        period = 1.0 / rate_hz
        t_next = time.perf_counter()
        for k in range(n):
            send(k)
            t_next += period
            while True:
                left = t_next - time.perf_counter()
                if left <= 0:
                    break
                spin(left)
        wait_until(lambda: len(received) >= n, 2.0, spin, 0.01)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    lat = np.array([received[k] - sent[k] for k in sent if k in received]) * 1e3
    return {"sent": len(sent), "received": int(lat.size), "lost": len(sent) - int(lat.size),
            "p50_ms": percentile(lat, 50) if lat.size else None, "p99_ms": percentile(lat, 99) if lat.size else None,
            "max_ms": float(lat.max()) if lat.size else None}


def realtime_stamps(seconds: float) -> list:
    """Stamps (ns) of every /pusher/state received during ``seconds``."""
    stamps: list = []
    arrivals: list = []
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("bench_realtime_probe", context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)

    def on_state(msg):
        stamps.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
        arrivals.append(time.perf_counter())

    node.create_subscription(JointState, "/pusher/state", on_state, 100)
    try:
        if not wait_until(lambda: len(stamps) > 10, 30.0, lambda t: executor.spin_once(timeout_sec=t)):
            raise RuntimeError("no /pusher/state from the realtime sim")
        stamps.clear()
        arrivals.clear()
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            executor.spin_once(timeout_sec=0.05)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    return stamps


class Echo(Node):
    """A bare echo node: answers each /pusher/state with a /policy/action of the same stamp."""

    def __init__(self):
        super().__init__("bench_echo")
        self.pub = self.create_publisher(JointState, "/policy/action", 10)
        self.create_subscription(JointState, "/pusher/state", self.on_state, 10)
        self.out = JointState(name=list(JOINT_NAMES))

    def on_state(self, msg):
        self.out.header.stamp = msg.header.stamp
        self.out.effort = [0.0, 0.0]
        self.pub.publish(self.out)


def echo() -> None:
    rclpy.init()
    node = Echo()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def online_actor(seconds: float) -> dict:
    """For ``seconds``: each /pusher/state (stamp, arrival), each answer reported on
    /policy/provenance (stamp, arrival, weights version and age) and each /learner/weights
    arrival, all on this process's monotonic clock."""
    from std_msgs.msg import String, UInt8MultiArray
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("bench_online_probe", context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    states, answers, weights = [], [], []

    def on_state(msg):
        states.append((msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec, time.monotonic()))

    def on_provenance(msg):
        info = json.loads(msg.data)
        answers.append((info["stamp"], time.monotonic(), info["weights_version"], info.get("weights_age_s")))

    node.create_subscription(JointState, "/pusher/state", on_state, 100)
    node.create_subscription(String, "/policy/provenance", on_provenance, 100)
    node.create_subscription(UInt8MultiArray, "/learner/weights", lambda m: weights.append(time.monotonic()),
                             QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                        durability=DurabilityPolicy.VOLATILE))
    # the window opens once every publisher is matched (and a second after, so no message of
    # the first tick is lost to discovery): what is missed then, the node missed
    topics = ("/pusher/state", "/policy/provenance", "/learner/weights")
    wait_until(lambda: all(node.count_publishers(t) for t in topics), 60, lambda t: executor.spin_once(timeout_sec=t))
    settle = time.monotonic() + 1.0
    while time.monotonic() < settle:
        executor.spin_once(timeout_sec=0.01)
    states.clear(), answers.clear(), weights.clear()
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.01)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown(context=ctx)
    return {"states": states, "answers": answers, "weights": weights}


def main(argv: list) -> int:
    if argv[:1] == ["echo"]:
        echo()
        return 0
    if argv[:1] == ["round-trip"] and len(argv) == 3:
        print(json.dumps(round_trip(int(argv[1]), float(argv[2]))))
        return 0
    if argv[:1] == ["online-actor"] and len(argv) == 2:
        print(json.dumps(online_actor(float(argv[1]))))
        return 0
    if argv[:1] == ["realtime-stamps"] and len(argv) == 2:
        print(json.dumps(realtime_stamps(float(argv[1]))))
        return 0
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
