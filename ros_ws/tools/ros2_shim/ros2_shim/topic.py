"""``ros2 topic list | echo | hz`` on rclpy, printing what ros2topic prints."""

from __future__ import annotations

import argparse
import importlib
import math
import sys
import time
from collections import OrderedDict, deque

from .graph import DISCOVERY_SPIN_S, cli_node, hidden, spin_for_discovery


def topic_command(args: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="ros2 topic", description="Various topic related sub-commands")
    sub = parser.add_subparsers(dest="verb", metavar="Commands")

    list_p = sub.add_parser("list", help="Output a list of available topics")
    list_p.add_argument("-t", "--show-types", action="store_true", help="Additionally show the topic type")
    list_p.add_argument("--include-hidden-topics", action="store_true", help="Consider hidden topics as well")
    list_p.add_argument("--spin-time", type=float, default=DISCOVERY_SPIN_S, help="Seconds to wait for discovery")

    echo_p = sub.add_parser("echo", help="Output messages from a topic")
    echo_p.add_argument("topic_name", help="Name of the ROS topic to listen to (e.g. '/chatter')")
    echo_p.add_argument("message_type", nargs="?", help="Type of the ROS message (e.g. 'std_msgs/msg/String')")
    echo_p.add_argument("--once", action="store_true", help="Print the first message received and then exit")
    echo_p.add_argument("--field", help="Echo a selected field of a message (e.g. 'header.stamp')")
    echo_p.add_argument("--full-length", "-f", action="store_true", help="Output all elements for arrays, bytes and strings")
    echo_p.add_argument("--truncate-length", "-l", type=int, default=128, help="Truncate arrays and strings longer than this")
    echo_p.add_argument("--no-arr", action="store_true", help="Don't print array fields of messages")
    echo_p.add_argument("--csv", action="store_true", help="Output all recursive fields separated by commas")
    echo_p.add_argument("--spin-time", type=float, default=DISCOVERY_SPIN_S, help=argparse.SUPPRESS)

    hz_p = sub.add_parser("hz", help="Print the average receiving rate to screen")
    hz_p.add_argument("topic_name", help="Name of the ROS topic to listen to (e.g. '/chatter')")
    hz_p.add_argument("--window", "-w", type=int, default=10000, help="Window size, in # of messages, for the statistics")
    hz_p.add_argument("--spin-time", type=float, default=DISCOVERY_SPIN_S, help=argparse.SUPPRESS)

    opts = parser.parse_args(args)
    if opts.verb is None:
        parser.print_help()
        return 2

    from rclpy.executors import ExternalShutdownException

    try:
        with cli_node() as node:
            if opts.verb == "list":
                return _list(node, opts)
            if opts.verb == "echo":
                return _echo(node, opts)
            return _hz(node, opts)
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0


# ---------------------------------------------------------------- list
def _list(node, opts) -> int:
    def topics():
        return sorted((name, tuple(types)) for name, types in node.get_topic_names_and_types())

    for name, types in spin_for_discovery(node, opts.spin_time, topics):
        if hidden(name) and not opts.include_hidden_topics:
            continue
        print(f"{name} [{', '.join(types)}]" if opts.show_types else name)
    return 0


def message_class(type_name: str):
    """'sensor_msgs/msg/JointState' (or 'sensor_msgs/JointState') -> the Python class."""
    parts = type_name.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3:
        raise ValueError(f"The passed message type '{type_name}' is invalid")
    module = importlib.import_module(f"{parts[0]}.{parts[1]}")
    return getattr(module, parts[2])


def _wait_for_topic(node, topic: str, spin_time: float):
    """The topic's type and publisher QoS, waiting for it to be published."""
    import rclpy

    start = time.monotonic()
    warned = False
    while True:
        rclpy.spin_once(node, timeout_sec=0.05)
        types = dict(node.get_topic_names_and_types()).get(topic)
        if types:
            return types[0], node.get_publishers_info_by_topic(topic)
        if not warned and time.monotonic() - start > max(spin_time, 1.0):
            print(f"WARNING: topic [{topic}] does not appear to be published yet", file=sys.stderr)
            warned = True


def _qos_for(publishers_info):
    """Match the publishers, as ros2topic does: reliable / transient local only if all offer it."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    qos = QoSProfile(depth=10)
    if publishers_info and all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in publishers_info):
        qos.reliability = ReliabilityPolicy.RELIABLE
    else:
        qos.reliability = ReliabilityPolicy.BEST_EFFORT
    if publishers_info and all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers_info):
        qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
    return qos


def _resolve(node, topic: str) -> str:
    return topic if topic.startswith("/") else node.resolve_topic_name(topic)


# ---------------------------------------------------------------- echo
def message_to_ordereddict(msg, truncate_length: int | None = None, no_arr: bool = False) -> OrderedDict:
    """A message as nested OrderedDicts / lists, like rosidl_runtime_py.message_to_ordereddict."""
    out = OrderedDict()
    for field, field_type in msg.get_fields_and_field_types().items():
        value = getattr(msg, field)
        if no_arr and ("sequence<" in field_type or field_type.endswith("]")):
            out[field] = f"<{field_type}, length: {len(value)}>"
            continue
        out[field] = _convert(value, truncate_length)
    return out


def _convert(value, truncate_length):
    if hasattr(value, "get_fields_and_field_types"):
        return message_to_ordereddict(value, truncate_length)
    if isinstance(value, (bytes, bytearray)):
        value = list(value)
    if hasattr(value, "tolist"):  # numpy arrays and array.array
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        items = list(value)
        truncated = truncate_length is not None and len(items) > truncate_length
        if truncated:
            items = items[:truncate_length]
        items = [_convert(v, truncate_length) for v in items]
        if truncated:
            items.append("...")
        return items
    if isinstance(value, str) and truncate_length is not None and len(value) > truncate_length:
        return value[:truncate_length] + "..."
    return value


def _yaml(data) -> str:
    import yaml

    class _Dumper(yaml.SafeDumper):
        pass

    _Dumper.add_representer(
        OrderedDict, lambda dumper, d: dumper.represent_mapping("tag:yaml.org,2002:map", d.items())
    )
    return yaml.dump(data, Dumper=_Dumper, default_flow_style=False, allow_unicode=True, width=math.inf)


def _csv(value) -> str:
    if isinstance(value, dict):
        return ",".join(_csv(v) for v in value.values())
    if isinstance(value, list):
        return ",".join(_csv(v) for v in value)
    return str(value)


def _echo(node, opts) -> int:
    import rclpy

    topic = _resolve(node, opts.topic_name)
    if opts.message_type:
        type_name, info = opts.message_type, node.get_publishers_info_by_topic(topic)
    else:
        type_name, info = _wait_for_topic(node, topic, opts.spin_time)
    try:
        msg_class = message_class(type_name)
    except (ImportError, AttributeError, ValueError):
        print(f"The message type '{type_name}' is invalid", file=sys.stderr)
        return 1
    truncate = None if opts.full_length else opts.truncate_length
    field_path = [f for f in (opts.field or "").split(".") if f]
    state = {"done": False}

    def on_message(msg):
        value = msg
        for f in field_path:
            value = getattr(value, f)
        if hasattr(value, "get_fields_and_field_types"):
            data = message_to_ordereddict(value, truncate, opts.no_arr)
        else:
            data = _convert(value, truncate)
        if opts.csv:
            print(_csv(data))
        elif isinstance(data, dict):
            sys.stdout.write(_yaml(data) + "---\n")
        else:
            sys.stdout.write(_yaml(data).removesuffix("...\n") + "---\n")
        sys.stdout.flush()
        if opts.once:
            state["done"] = True

    node.create_subscription(msg_class, topic, on_message, _qos_for(info))
    while not state["done"]:
        rclpy.spin_once(node, timeout_sec=0.1)
    return 0


# ---------------------------------------------------------------- hz
def _hz(node, opts) -> int:
    import rclpy

    topic = _resolve(node, opts.topic_name)
    type_name, info = _wait_for_topic(node, topic, opts.spin_time)
    msg_class = message_class(type_name)
    arrivals: deque[float] = deque(maxlen=opts.window + 1)

    def on_message(_raw):
        arrivals.append(time.monotonic())

    node.create_subscription(msg_class, topic, on_message, _qos_for(info), raw=True)
    last_print = time.monotonic()
    while True:
        rclpy.spin_once(node, timeout_sec=0.05)
        now = time.monotonic()
        if now - last_print < 1.0:
            continue
        last_print = now
        if len(arrivals) < 2:
            continue  # like ros2 topic hz: silent until there is a rate to show
        stamps = list(arrivals)
        deltas = [b - a for a, b in zip(stamps, stamps[1:])]
        mean = sum(deltas) / len(deltas)
        std = math.sqrt(sum((d - mean) ** 2 for d in deltas) / len(deltas))
        print(f"average rate: {1.0 / mean:.3f}")
        print(f"\tmin: {min(deltas):.3f}s max: {max(deltas):.3f}s std dev: {std:.5f}s window: {len(stamps)}")
        sys.stdout.flush()
