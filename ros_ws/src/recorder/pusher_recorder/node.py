"""``ros2 run recorder node``: record a rosbag2 bag (by default, drive the sim too).

By default it drives the sim to record a pusher-reach dataset.

Active (default): drives the sim with the scripted expert for the first
``round(expert_frac * episodes)`` episodes and uniform random actions after, exactly as
``offline-rl collect`` does in process, and records ``pusher/transition`` plus
``pusher/state``, ``pusher/target``, the commands it sends on ``pusher/command/expert``
and ``pusher/command/random`` (who acted is the topic, as the sim reads it), and any
``topics`` given. Against a lockstep sim started with the same seed the bag's
transitions equal ``offline-rl collect``'s bit for bit.

  ros2 run recorder node --out bags/mix.db3 --episodes 200 --expert-frac 0.3 --seed 0

``--passive`` records what flows (a policy or a person driving): the ``topics`` given,
or every topic as it appears (like ``ros2 bag record -a``: ``/diagnostics`` and the arm's
``markers`` too, so a bag replayed into Foxglove or RViz shows the arm and the nodes' health;
``--exclude-topic-types visualization_msgs/msg/MarkerArray diagnostic_msgs/msg/DiagnosticArray``
leaves them out, as ``ros2 bag record``'s flag does), until Ctrl-C, or until
``episodes`` episodes have ended when given. ``pusher/transition`` and ``episode_label`` (a
person's labels of episodes, ``offline_rl_core.data.episode_labels``) are subscribed from the
start, before discovery finds their publishers. Each topic is subscribed with a QoS its
publishers offer (reliable only when they all are, transient local likewise), and the
bag keeps their offered QoS, as ``ros2 bag record`` does. Topic names are relative:
``--ros-args -r __ns:=/arm2`` records that namespace's pipeline.

Messages are stamped with the node's clock (sim time with ``-p use_sim_time:=true``),
strictly increasing so the bag's order is the arrival order. Under sim time a message gets
the sim time current when it was published (``offline_rl_core.nodes.publication_clock``), not
when the recorder got to it: a command is not stamped with the /clock of the step it caused;
the bag's order is then the publication order. Ctrl-C or SIGTERM close the
bag with every message received; a SIGKILL loses at most the last ``flush_interval``
(at most 1 s) of messages (``offline_rl_core.data.bag.recording``). When the bag's file
system has less than ``min_free_space`` left, the recorder stops: the bag is closed whole
with every message before the stop, and the node exits with status 1.

A topic whose type discovery reports in a form that is no ``pkg/msg/Name`` (or whose
package is not installed) is skipped with one warning. Under ``use_sim_time``, messages
that come before the first ``/clock`` wait for it, at most ``BEFORE_CLOCK_BYTES`` of them
(the oldest are dropped beyond that, counted in the closing line).

Who acts, episode counting and the command/transition handshake are
``offline_rl_core.nodes.collect_driver.CollectDriver`` (free of ROS, its docstring gives the
protocol); this node subscribes, publishes and writes the bag.
"""

from __future__ import annotations

import sys
import time
from collections import deque
from pathlib import Path

from geometry_msgs.msg import PointStamped
from rclpy.clock import Clock as NodeClock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from rclpy.task import Future
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from sensor_msgs.msg import JointState
from std_msgs.msg import Float32MultiArray, String

from offline_rl_core.data.bag import BagWriter, transition_ends_episode, typestore
from offline_rl_core.data.bag.recording import MIN_SQLITE_SPLIT_SIZE, OutOfSpace
from offline_rl_core.data.collect import EpisodePlan
from offline_rl_core.data.episode_labels import LABEL_MSGTYPE, LABEL_TOPIC
from offline_rl_core.nodes.publication_clock import PublicationClock, published_ns
from offline_rl_core.nodes.collect_driver import CollectDriver, Command
from offline_rl_core.task.pusher_reach import JOINT_NAMES
from offline_rl_core.common.errors import UserError
from offline_rl_core.common.output_paths import check_output_dir
from offline_rl_core.data.transitions import SOURCE_EXPERT, SOURCE_NAMES, SOURCE_RANDOM
from pusher_common.message_types import MESSAGE_TYPE, message_class
from pusher_common.node_main import run_node
from pusher_common.params import Param, Settings
from pusher_common.spin import spin_until_future_complete
from pusher_common.stamps import stamp_from_ns, stamp_key
from pusher_common.diagnostics import NodeDiagnostics
from offline_rl_core.nodes.diagnostics import StatusDiagnosis, recorder_checks

# The loop's topics, relative to the node's namespace, and their types.
TRANSITION, STATE, TARGET, COMMAND = "pusher/transition", "pusher/state", "pusher/target", "pusher/command"
LOOP_TYPES = {
    TRANSITION: ("std_msgs/msg/Float32MultiArray", Float32MultiArray),
    STATE: ("sensor_msgs/msg/JointState", JointState),
    TARGET: ("geometry_msgs/msg/PointStamped", PointStamped),
    COMMAND: ("sensor_msgs/msg/JointState", JointState),
}
DISCOVERY_PERIOD_S = 0.5
BEFORE_CLOCK_BYTES = 64 << 20  # what may wait for the first /clock under use_sim_time

PARAMS = (
    Param("out", "", "bag to write: x.db3 / x.mcap (one file) or a directory (metadata.yaml + x_0.db3, x_1.db3, ...)",
          read_only=True, flag="--out"),
    Param("passive", False, "only record what flows, until stopped (or until `episodes` episodes end)",
          read_only=True, flag="--passive"),
    Param("episodes", 0, "episodes to record (required when driving; passive: 0 = until stopped)", low=0,
          read_only=True, flag="--episodes"),
    Param("expert_frac", 0.3, "fraction of expert episodes, first (driving)", low=0.0, high=1.0, read_only=True,
          flag="--expert-frac"),
    Param("seed", 0, "seed of the random-action generator (driving)", read_only=True, flag="--seed"),
    Param("storage", "", "sqlite3 or mcap (default: from out's suffix, else sqlite3)", choices=("", "sqlite3", "mcap"),
          read_only=True, flag="--storage"),
    Param("overwrite", False, "replace an existing bag at out (it is deleted at start)", read_only=True,
          flag="--overwrite"),
    # a bag's directory must exist (as for offline-rl collect), unless a launch file naming a
    # new session directory asks for it to be made
    Param("make_parents", False, "create out's missing parent directories (off: a missing directory is refused "
          "at start)", read_only=True, flag="--make-parents"),
    Param("topics", [], "topics to record (relative names resolve in the node's namespace); none: every topic when "
          "passive, the loop's when driving", read_only=True, flag="--topics", kind=list),
    Param("exclude_topic_types", [], "message types left out when recording every topic (e.g. "
          "visualization_msgs/msg/MarkerArray diagnostic_msgs/msg/DiagnosticArray: the arm's markers and the nodes' "
          "health, which every topic includes); a topic named in topics is recorded whatever its type",
          read_only=True, flag="--exclude-topic-types", kind=list),
    Param("types", [], "TOPIC:TYPE pairs (e.g. joint_states:sensor_msgs/msg/JointState) to record from the start, "
          "subscribed reliable at once rather than when discovery finds their publishers: a session's first messages "
          "are in the bag however slowly discovery goes", read_only=True, flag="--types", kind=list),
    Param("flush_interval", 1.0, "seconds between writes to disk: a kill loses at most this much (at most 1 s, "
          "the recorder's promise)", low=0.001, high=1.0, flag="--flush-interval"),
    Param("min_free_space", 128 << 20, "stop recording (the bag closed whole, exit 1) when the bag's file system "
          "has fewer bytes free than this (0: never)", low=0, flag="--min-free-space"),
    Param("max_bag_size", 0, "start a new file of the bag directory past this many bytes (0: never)", low=0,
          flag="--max-bag-size"),
    Param("max_bag_duration", 0.0, "start a new file of the bag directory after this many seconds of stamps (0: never)",
          low=0.0, flag="--max-bag-duration"),
)
TRANSITION_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def _qos_time(duration) -> QosTime:
    ns = duration.nanoseconds
    if ns >= 2**63 - 1 or ns < 0:  # rmw's "infinite", as rosbag2 writes it
        return QosTime(2147483647, 4294967295)
    return QosTime(*divmod(ns, 10**9))


def _enum(enum, policy):
    return enum.__members__.get(getattr(policy, "name", ""), enum.__members__["UNKNOWN"])


def offered_qos(infos) -> list[Qos]:
    """Return the publishers' QoS profiles, as the bag's metadata records them."""
    return [
        Qos(
            _enum(QosHistory, q.history), q.depth, _enum(QosReliability, q.reliability),
            _enum(QosDurability, q.durability), _qos_time(q.deadline), _qos_time(q.lifespan),
            _enum(QosLiveliness, q.liveliness), _qos_time(q.liveliness_lease_duration),
            q.avoid_ros_namespace_conventions,
        )
        for q in (info.qos_profile for info in infos)
    ]


def subscription_qos(infos, depth: int) -> QoSProfile:
    """Return a QoS every publisher's offer matches (reliable, transient local if all are)."""
    profiles = [info.qos_profile for info in infos]
    reliable = profiles and all(q.reliability == ReliabilityPolicy.RELIABLE for q in profiles)
    latched = profiles and all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in profiles)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def hidden(topic: str) -> bool:
    return any(part.startswith("_") for part in topic.split("/"))


class Recorder(Node):
    def __init__(self, overrides=()):
        super().__init__("recorder", parameter_overrides=list(overrides))
        self.settings = s = Settings(self, PARAMS, on_change=self.on_parameter_change, check=self.check_parameter)
        if not s.out:
            raise UserError("no bag given: pass --out PATH or -p out:=PATH")
        self.active = not s.passive
        if self.active and s.episodes < 1:
            raise UserError("--episodes is required when driving the sim (or --passive to only record)")
        self.episodes = s.episodes or None
        plan = EpisodePlan(s.episodes, s.expert_frac, s.seed) if self.active else None
        self.driver = CollectDriver(self.episodes, plan)
        self.finished = Future()
        self.exit_code = 0
        self.last_stamp_ns = 0
        self.before_clock: deque[tuple[str, bytes]] = deque()  # (topic, message) received before sim time starts
        self.before_clock_bytes = 0
        self.dropped_before_clock = 0
        self.start_time = time.monotonic()
        self.progress_tty = sys.stderr.isatty()
        self.last_progress_decile = -1
        self.warned: set[str] = set()

        self.matched = False  # the active loop's topics have all matched (see connected)
        # sim time by publication: this /clock subscription comes before every recorded topic's
        self.publication_clock = None
        if self.get_parameter("use_sim_time").value:
            self.publication_clock = PublicationClock()
            self.clock_sub = self.create_subscription(Clock, "/clock", self.on_clock, QoSProfile(
                depth=100, reliability=ReliabilityPolicy.RELIABLE), raw=True)

        if s.make_parents:  # a launch file's new session directory; the bag itself is checked by BagWriter
            parent = check_output_dir(Path(s.out).parent, "--out")
            parent.mkdir(parents=True, exist_ok=True)
        self.bag = BagWriter(s.out, storage=s.storage or None, overwrite=s.overwrite, flush_interval=s.flush_interval,
                             max_bag_size=s.max_bag_size, max_bag_duration=s.max_bag_duration,
                             min_free_space=s.min_free_space)
        self.record_all = self.active is False and not s.topics
        self.wanted = {self.resolve(t) for t in s.topics or ()}
        self.excluded_types = set(s.exclude_topic_types or ())
        for msgtype in sorted(self.excluded_types):
            if not MESSAGE_TYPE.fullmatch(msgtype):
                raise UserError(f"--exclude-topic-types {msgtype}: expected a message type pkg/msg/Name, e.g. "
                                "visualization_msgs/msg/MarkerArray")
        self.subs: dict[str, object] = {}  # resolved name -> subscription
        self.bag_topics: set[str] = set()  # added to the bag (at their first message)
        self.types: dict[str, str] = {}  # resolved name -> message type
        self.transition_topic = self.resolve(TRANSITION)
        if self.active:
            loop = (TRANSITION, STATE, TARGET)
        else:  # the dataset's topic from the start, not after discovery
            loop = (TRANSITION,) if self.record_all or self.transition_topic in self.wanted else ()
        for topic in loop:
            self.subscribe(self.resolve(topic), *LOOP_TYPES[topic], TRANSITION_QOS if topic == TRANSITION else 10)
        if self.active is False and (self.record_all or self.resolve(LABEL_TOPIC) in self.wanted):
            # a person's episode labels from the start too: one pressed before discovery finds its publisher is kept
            self.subscribe(self.resolve(LABEL_TOPIC), LABEL_MSGTYPE, String, 10)
        for pair in s.types or ():
            topic, _, msgtype = pair.partition(":")
            msg_class = message_class(msgtype)
            if not topic or msg_class is None:
                raise UserError(f"--types {pair}: expected TOPIC:TYPE with an installed type, e.g. "
                                "joint_states:sensor_msgs/msg/JointState")
            self.wanted.add(self.resolve(topic))
            if self.resolve(topic) not in self.subs:
                self.subscribe(self.resolve(topic), msgtype, msg_class, TRANSITION_QOS)
        if self.active:
            # who acted is the topic, as the sim reads it: pusher/command/expert or .../random
            self.command_pubs = {source: self.create_publisher(JointState, f"{COMMAND}/{SOURCE_NAMES[source]}", 10)
                                 for source in (SOURCE_EXPERT, SOURCE_RANDOM)}
            self.create_timer(0.1, self.try_act)
        # Other topics are subscribed as discovery finds their publishers (and types).
        self.dynamic = self.record_all or bool(self.wanted - set(self.subs))
        if self.dynamic:
            # wall time: under use_sim_time a sim that holds its first state (and /clock) until
            # this recorder reads its topics would otherwise wait for a discovery that never runs
            self.create_timer(DISCOVERY_PERIOD_S, self.discover, clock=NodeClock(clock_type=ClockType.STEADY_TIME))
            self.discover()
        self.diagnostics = NodeDiagnostics(self, self.status, StatusDiagnosis(
            checks=(recorder_checks,), idle=lambda st: f"recording to {self.bag.path}"))
        what = f"{self.episodes} episodes ({plan.n_expert} expert)" if self.active else "passively"
        which = "every topic" if self.record_all else ", ".join(sorted(self.wanted | set(self.subs)))
        self.get_logger().info(f"recording {what} to {self.bag.path}: {which}")

    def resolve(self, topic: str) -> str:
        return self.resolve_topic_name(topic)

    def status(self) -> dict:
        """Report for /diagnostics: counts, the disk's lag, and what stops the recording."""
        error = self.bag.error
        return {"messages": self.bag.message_count, "topics": len(self.bag_topics),
                "transitions": self.driver.transitions, "episodes_done": self.driver.episodes_done,
                "flush_lag_s": round(self.bag.flush_lag_s(), 3), "flush_interval_s": self.bag.flush_interval,
                "low_space_bytes": self.bag.low_space, "dropped_before_clock": self.dropped_before_clock,
                "error": None if error is None else f"{type(error).__name__}: {error}",
                "finished": self.finished.done()}

    # -------------------------------------------------------------- parameters
    def check_parameter(self, name: str, value) -> str | None:
        if name in ("max_bag_size", "max_bag_duration") and value and self.bag.target.single_file:
            return f"splitting needs a bag directory as output, not {self.bag.path}"
        if name == "max_bag_size" and self.bag.storage_id == "sqlite3" and 0 < value < MIN_SQLITE_SPLIT_SIZE:
            return f"below the sqlite3 minimum of {MIN_SQLITE_SPLIT_SIZE} bytes"
        return None

    def on_parameter_change(self, name: str, value) -> None:
        if name == "flush_interval":
            self.bag.flush_interval = float(value)
        elif name == "max_bag_size":
            self.bag.max_bag_size = int(value)
        elif name == "max_bag_duration":
            self.bag.max_bag_duration_ns = int(value * 1e9)
        elif name == "min_free_space":
            self.bag.min_free_space = int(value)

    # -------------------------------------------------------------- subscribing
    def subscribe(self, topic: str, msgtype: str, msg_class, qos) -> None:
        self.types[topic] = msgtype
        self.subs[topic] = self.create_subscription(msg_class, topic, self.make_callback(topic), qos, raw=True)

    def warn_once(self, key: str, text: str) -> None:
        if key not in self.warned:
            self.warned.add(key)
            self.get_logger().warn(text)

    def discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self.subs or not (topic in self.wanted or (self.record_all and not hidden(topic))):
                continue
            if self.active and topic in (pub.topic_name for pub in self.command_pubs.values()):
                continue  # written as sent (see send)
            if topic not in self.wanted and set(types) & self.excluded_types:
                continue
            if len(types) != 1:
                self.warn_once(topic, f"not recording {topic}: published with several types ({', '.join(types)})")
                continue
            msg_class = message_class(types[0])
            if msg_class is None:
                why = "is not installed here" if MESSAGE_TYPE.fullmatch(types[0]) else "is not a pkg/msg/Name type"
                self.warn_once(topic, f"not recording {topic}: its type {types[0][:80]!r} {why}")
                continue
            infos = self.get_publishers_info_by_topic(topic)
            if infos:  # subscribe with what they offer
                depth = 1000 if topic == self.transition_topic else 100
                self.subscribe(topic, types[0], msg_class, subscription_qos(infos, depth))
                self.get_logger().info(f"subscribed to {topic} ({types[0]})")  # as ros2 bag record says

    def add_to_bag(self, topic: str, msgtype: str, infos) -> None:
        msgdef = rihs01 = None
        if msgtype not in typestore().fielddefs:  # not a standard type: its hash, no definition
            msgdef, rihs01 = "", str(infos[0].topic_type_hash) if infos else ""
        self.bag.add_topic(topic, msgtype, msgdef=msgdef, rihs01=rihs01, offered_qos_profiles=offered_qos(infos))

    # -------------------------------------------------------------- recording
    def on_clock(self, raw: bytes, info) -> None:
        clock = deserialize_message(raw, Clock).clock
        released = self.publication_clock.add_clock(published_ns(info), clock.sec * 1_000_000_000 + clock.nanosec)
        self.write_released(released)

    def write_released(self, released) -> None:
        for stamp, (topic, raw) in released:
            if self.finished.done():
                return
            self.write_stamped(topic, stamp, raw, by_publication=True)

    def take_clocks(self) -> None:
        """Take every /clock already received, before a message is stamped.

        A callback takes one message per subscription a turn: a recorder behind by two ticks
        would else stamp a message by the older one.
        """
        while (taken := self.clock_sub.handle.take_message(Clock, True)) is not None:
            self.on_clock(*taken)

    def make_callback(self, topic: str):
        def on_raw(raw: bytes, info) -> None:
            self.write(topic, raw, published_ns(info))
            if topic == self.transition_topic:
                self.on_transition(raw)
            elif self.active and topic == self.resolve(STATE):
                self.on_state(deserialize_message(raw, JointState))
            elif self.active and topic == self.resolve(TARGET):
                self.on_target(deserialize_message(raw, PointStamped))

        return on_raw

    def write(self, topic: str, raw: bytes, published: int | None = None) -> None:
        if self.finished.done():
            return
        if self.bag.low_space is not None:
            self.stop_for_space()
            return
        if topic not in self.bag_topics:
            self.add_to_bag(topic, self.types[topic], self.get_publishers_info_by_topic(topic))
            self.bag_topics.add(topic)
        if self.publication_clock is not None and published is not None:
            self.take_clocks()
            self.write_released(self.publication_clock.add(published, (topic, raw)))
            return
        now_ns = self.get_clock().now().nanoseconds
        if now_ns == 0:
            # sim time before the first /clock: held until the clock starts, so no message
            # is stamped at the epoch (ros2 bag record would); bounded: the oldest go first
            self.before_clock.append((topic, raw))
            self.before_clock_bytes += len(raw)
            while self.before_clock_bytes > BEFORE_CLOCK_BYTES:
                self.before_clock_bytes -= len(self.before_clock.popleft()[1])
                self.dropped_before_clock += 1
                self.warn_once("before clock", f"no /clock yet: dropping the oldest of the messages waiting "
                                               f"for it (more than {BEFORE_CLOCK_BYTES >> 20} MiB)")
            return
        for held_topic, held_raw in self.before_clock:
            self.write_stamped(held_topic, now_ns, held_raw)
        self.before_clock.clear()
        self.before_clock_bytes = 0
        self.write_stamped(topic, now_ns, raw)

    def write_stamped(self, topic: str, now_ns: int, raw: bytes, by_publication: bool = False) -> None:
        # The node's clock (sim time when use_sim_time is set), strictly increasing so the
        # bag's order is the arrival order; a stamp by publication says that order itself
        # (callbacks may run out of it).
        stamp = now_ns if by_publication else max(now_ns, self.last_stamp_ns + 1)
        self.last_stamp_ns = stamp
        try:
            self.bag.write(topic, stamp, raw)
        except OutOfSpace:  # the flush thread found the disk nearly full since write() looked
            self.stop_for_space()

    def on_transition(self, raw: bytes) -> None:
        if self.finished.done():
            return
        if self.driver.on_transition(transition_ends_episode(raw)):
            self.show_progress()
            if self.driver.finished:
                self.finish()
                return
        self.try_act()

    def show_progress(self) -> None:
        if not self.episodes:
            return
        done, transitions = self.driver.episodes_done, self.driver.transitions
        elapsed = max(time.monotonic() - self.start_time, 1e-9)
        line = (
            f"recorder: {done}/{self.episodes} episodes, {transitions} transitions, "
            f"{transitions / elapsed:.0f} transitions/s"
        )
        if self.progress_tty:
            end = "\n" if done >= self.episodes else ""
            print("\r" + line, end=end, file=sys.stderr, flush=True)
            return
        decile = 10 * done // self.episodes
        if decile != self.last_progress_decile:
            self.last_progress_decile = decile
            print(line, file=sys.stderr, flush=True)

    # -------------------------------------------------------------- driving
    def on_state(self, msg: JointState) -> None:
        again = self.driver.on_state(stamp_key(msg.header.stamp), msg.position, msg.velocity)
        if again is not None:  # the sim republished the state we answered: our command was lost
            self.send(again)
            return
        self.try_act()

    def on_target(self, msg: PointStamped) -> None:
        self.driver.on_target(stamp_key(msg.header.stamp), (msg.point.x, msg.point.y))
        self.try_act()

    def connected(self) -> bool:
        """Sim and recorder have matched on every topic of the loop (checked until true)."""
        if not self.matched:
            self.matched = (
                all(self.subs[self.resolve(t)].get_publisher_count() > 0 for t in (TRANSITION, STATE, TARGET))
                and all(pub.get_subscription_count() > 0 for pub in self.command_pubs.values())
            )
        return self.matched

    def try_act(self) -> None:
        if self.active and not self.finished.done() and self.driver.ready() and self.connected():
            self.send(self.driver.next_command())

    def send(self, command: Command) -> None:
        msg = JointState(name=list(JOINT_NAMES), effort=[float(a) for a in command.action])
        msg.header.stamp = stamp_from_ns(command.stamp)  # the answered state's
        publisher = self.command_pubs[command.source]
        publisher.publish(msg)
        topic = publisher.topic_name
        if topic not in self.types:
            self.types[topic] = LOOP_TYPES[COMMAND][0]
        self.write(topic, serialize_message(msg))

    # -------------------------------------------------------------- the end
    def stop_for_space(self) -> None:
        """End the recording now, the bag whole, as the disk is nearly full (exit status 1)."""
        if self.finished.done():
            return
        print(f"recorder: error: only {self.bag.low_space >> 20} MiB free for {self.bag.path}, below "
              f"min_free_space ({self.bag.min_free_space >> 20} MiB): recording stopped, the bag holds every "
              f"message before the stop", file=sys.stderr)
        self.exit_code = 1
        self.finish()

    def finish(self) -> None:
        """All episodes are in: close the bag now, so its outcome sets the exit status."""
        if not self.finished.done():
            self.finished.set_result(True)
        self.close_bag()

    def close_bag(self) -> None:
        if self.publication_clock is not None:  # what waits for a later /clock: by the last one
            self.take_clocks()
            for stamp, (topic, raw) in self.publication_clock.flush():
                if stamp is None:
                    self.before_clock.append((topic, raw))
                else:
                    self.write_stamped(topic, stamp, raw, by_publication=True)
        if self.before_clock:  # /clock never came: keep the messages, stamped with the wall clock
            self.get_logger().warn(f"no /clock came: {len(self.before_clock)} messages stamped with the wall clock")
            held, self.before_clock = self.before_clock, deque()
            for topic, raw in held:
                self.write_stamped(topic, time.time_ns(), raw)
        try:
            self.bag.close()  # every message received is in the bag, however we got here
        except UserError as exc:
            print(f"recorder: error: {exc}", file=sys.stderr)
            self.exit_code = 2

    def close(self) -> None:
        """Close the bag: run_node calls it on every way out (done, Ctrl-C, SIGTERM, an error)."""
        interrupted = not self.finished.done()
        self.close_bag()
        elapsed = time.monotonic() - self.start_time
        driver = self.driver
        print(
            f"recorder: {'interrupted; ' if interrupted else ''}wrote {driver.transitions} transitions "
            f"({driver.episodes_done} episodes, {self.bag.message_count} messages) to {self.bag.path} "
            f"in {elapsed:.1f} s" + (f"; {self.dropped_before_clock} dropped while waiting for /clock"
                                     if self.dropped_before_clock else ""),
            file=sys.stderr,
        )


def spin_recorder(executor, node: Recorder) -> None:
    """Spin the recorder until it is done.

    The fast spin when every subscription exists from the start; rclpy's own when
    discovery adds subscriptions while recording.
    """
    if node.dynamic:
        executor.spin_until_future_complete(node.finished)
    else:
        spin_until_future_complete(executor, node.finished)


def expand_topics(argv: list[str]) -> list[str]:
    """Expand ``--topics a b c`` (as ``ros2 bag record`` takes it) to ``--topics a ...``.

    ``--types`` and ``--exclude-topic-types`` likewise.
    """
    out, i = [], 0
    while i < len(argv):
        out.append(argv[i])
        if argv[i] == "--ros-args":
            return out + argv[i + 1:]
        flag = argv[i]
        if flag in ("--topics", "--types", "--exclude-topic-types"):
            i += 1
            names = []
            while i < len(argv) and not argv[i].startswith("-"):
                names.append(argv[i])
                i += 1
            out.pop()
            for name in names or [""]:
                out += [flag, name] if name else [flag]
            continue
        i += 1
    return out


def main(argv: list[str] | None = None) -> int:
    argv = expand_topics(list(sys.argv if argv is None else argv))
    return run_node(Recorder, prog="recorder", command="ros2 run recorder node", flags=PARAMS, argv=argv,
                    spin=spin_recorder, description=__doc__.split("\n\n")[0])


if __name__ == "__main__":
    sys.exit(main())
