"""``ros2 run viz live_view``: the pipeline live in Foxglove through its WebSocket server, no ROS tooling needed.

Subscribes to ``topics`` (relative names resolve in the node's namespace) as their
publishers appear, and streams each message's CDR bytes on a Foxglove channel of the same
name (``offline_rl_core.nodes.live_view``): open Foxglove, connect to
``ws://127.0.0.1:8765`` and load ``share/viz/config/foxglove_layout.json``. Listens on
``host`` (loopback by default: the server has no authentication) and ``port`` (0: a free
one; the start-up line names it). Needs the ``viz`` extra (foxglove-sdk).
"""

from __future__ import annotations

import sys

from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, DurabilityPolicy

from offline_rl_core.nodes.live_view import DEFAULT_PORT, LOOPBACK, LiveView
from pusher_common.node_main import run_node
from pusher_common.params import Param, Settings

DEFAULT_TOPICS = ["markers", "pusher/state", "joint_states", "pusher/target", "goal", "pusher/transition",
                  "corrections/intervening", "episode_label", "/diagnostics"]
DISCOVERY_PERIOD_S = 0.5

PARAMS = (
    Param("host", LOOPBACK, "address the WebSocket server listens on (loopback: this machine only)",
          read_only=True, flag="--host"),
    Param("port", DEFAULT_PORT, "its port (0: a free one, named in the start-up line)", low=0, high=65535,
          read_only=True, flag="--port"),
    Param("topics", DEFAULT_TOPICS, "topics streamed, each as it appears", read_only=True, flag="--topics",
          kind=list),
)


class LiveViewNode(Node):
    def __init__(self, overrides=()):
        super().__init__("live_view", parameter_overrides=list(overrides))
        self.settings = s = Settings(self, PARAMS)
        self.view = LiveView(s.host, s.port)
        self.wanted = {self.resolve_topic_name(t) for t in s.topics}
        self.subs: dict[str, object] = {}
        self.create_timer(DISCOVERY_PERIOD_S, self.discover)
        self.discover()
        self.get_logger().info(f"live view on {self.view.url}: {', '.join(sorted(self.wanted))}")

    def discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self.subs or topic not in self.wanted or len(types) != 1:
                continue
            try:
                self.view.add_topic(topic, types[0])
            except KeyError:
                self.get_logger().warning(f"not streaming {topic}: its type {types[0]} is not known here")
                self.subs[topic] = None
                continue
            infos = self.get_publishers_info_by_topic(topic)
            reliable = infos and all(i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
            latched = infos and all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
            qos = QoSProfile(depth=100,
                             reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
            self.subs[topic] = self.create_subscription(
                self.message_class(types[0]), topic, lambda raw, t=topic: self.on_raw(t, raw), qos, raw=True)
            self.get_logger().info(f"streaming {topic} ({types[0]})")

    @staticmethod
    def message_class(msgtype: str):
        import importlib

        package, _, name = msgtype.split("/")
        return getattr(importlib.import_module(f"{package}.msg"), name)

    def on_raw(self, topic: str, raw: bytes) -> None:
        self.view.log(topic, raw, self.get_clock().now().nanoseconds)

    def close(self) -> None:
        self.view.close()


def main(argv: list[str] | None = None) -> int:
    return run_node(LiveViewNode, prog="live_view", command="ros2 run viz live_view", flags=PARAMS, argv=argv,
                    description="Stream the pipeline's topics to Foxglove over its WebSocket server.")


if __name__ == "__main__":
    sys.exit(main())
