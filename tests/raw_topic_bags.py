"""Raw-topic bags written in process: the env driven as `offline-rl collect` drives it, its
messages published into a rosbag2 bag as the sim node publishes them (or as a real arm's
log would hold them), serialized with the ROS 2 message definitions.

``sim_like=True``: the sim node's lockstep stream, stamp ``(e * 100 + t) * 20 ms``, no state
after an episode's last step; some states and commands appear twice, as the sim's
republishing and the recorder's resending put them in a bag. ``sim_like=False``: a real
arm's log, its state after the last step included, episodes apart in time.
"""

from __future__ import annotations

import numpy as np

from offline_rl_core.data.bag import BagWriter, encode_transition_rows, typestore
from offline_rl_core.task.pusher_reach import ACT_DIM, JOINT_NAMES, MAX_STEPS, PusherReachEnv
from offline_rl_core.data.collect import EpisodePlan
from offline_rl_core.data.episode_labels import encode_label_message
from offline_rl_core.data.transitions import LAYOUT_SLICES, SOURCE_NAMES, TRANSITION_WIDTH

TICK_NS = 20_000_000
START_NS = 1_735_689_600 * 10**9
TYPES = {
    "/pusher/state": "sensor_msgs/msg/JointState",
    "/pusher/target": "geometry_msgs/msg/PointStamped",
    "/pusher/fingertip": "geometry_msgs/msg/PointStamped",
    "/pusher/command": "sensor_msgs/msg/JointState",  # written to .../command/<source> (see record_raw_bag)
    "/pusher/transition": "std_msgs/msg/Float32MultiArray",
    "/pusher/reset": "std_msgs/msg/Empty",
}
RAW_TOPICS = ("/pusher/state", "/pusher/target", "/pusher/command")  # what any arm logs
SIM_TOPICS = ("/pusher/state", "/pusher/target", "/pusher/fingertip", "/pusher/command", "/pusher/transition")


class _Messages:
    def __init__(self):
        ts = typestore()
        self.ts = ts
        self.T = ts.types["builtin_interfaces/msg/Time"]
        self.H = ts.types["std_msgs/msg/Header"]
        self.JS = ts.types["sensor_msgs/msg/JointState"]
        self.PS = ts.types["geometry_msgs/msg/PointStamped"]
        self.P = ts.types["geometry_msgs/msg/Point"]
        self.F64 = ts.types["std_msgs/msg/Float64MultiArray"]
        self.L = ts.types["std_msgs/msg/MultiArrayLayout"]
        self.D = ts.types["std_msgs/msg/MultiArrayDimension"]

    def header(self, ns: int, frame_id: str):
        return self.H(stamp=self.T(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame_id)

    def joint_state(self, ns, frame_id, position=(), velocity=(), effort=(), names=JOINT_NAMES) -> bytes:
        msg = self.JS(header=self.header(ns, frame_id), name=list(names), position=np.array(position, np.float64),
                      velocity=np.array(velocity, np.float64), effort=np.array(effort, np.float64))
        return bytes(self.ts.serialize_cdr(msg, "sensor_msgs/msg/JointState"))

    def point(self, ns, xyz) -> bytes:
        msg = self.PS(header=self.header(ns, "world"), point=self.P(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])))
        return bytes(self.ts.serialize_cdr(msg, "geometry_msgs/msg/PointStamped"))

    def empty(self) -> bytes:
        return bytes(self.ts.serialize_cdr(self.ts.types["std_msgs/msg/Empty"](), "std_msgs/msg/Empty"))

    def float64_array(self, values) -> bytes:
        msg = self.F64(layout=self.L(dim=[], data_offset=0), data=np.array(values, np.float64))
        return bytes(self.ts.serialize_cdr(msg, "std_msgs/msg/Float64MultiArray"))


def record_raw_bag(
    path,
    episodes: int,
    expert_frac: float,
    seed: int,
    *,
    sim_like: bool = True,
    topics: tuple[str, ...] = SIM_TOPICS,
    drop: float = 0.0,
    jitter_ns: int = 0,
    duplicates: float = 0.0,
    torque_commands: bool = False,
    source_tags: bool = False,
    noise_seed: int = 1,
    estop: tuple[tuple[int, bool], ...] = (),
    late_resends: float = 0.0,
    republishes: float = 0.0,
    labels: tuple[tuple[int, bool], ...] = (),
) -> None:
    """Roll out ``episodes`` as `offline-rl collect` does and write their raw topics.

    ``drop``: share of state and of command messages left out; ``jitter_ns``: uniform
    +/- jitter on every header stamp (targets' included); ``duplicates``: share of states
    and commands written twice; ``torque_commands``: commands as std_msgs/Float64MultiArray
    torques (action * 0.5 N·m, the motors' gear) on /pusher/effort_controller/commands,
    with receive times 0.5 ms after the commanded state's (a recording in sim time).
    Commands go, as the sim takes them, to /pusher/command/<source>; ``source_tags``: to
    /pusher/command with the source in header.frame_id, as older recorders sent them.
    ``estop``: (receive stamp, value) of /estop (std_msgs/Bool) messages to record too.
    ``late_resends``: share of commands sent once more after the next state, before that
    state's own (the mux answering a republished state late: its stamp, received later).
    ``republishes``: share of states published again after their command (a lockstep sim's
    paced wait), the command then sent again (the mux answering the copy).
    ``labels``: (receive stamp, success) of a person's /episode_label messages, without an
    episode number, to record too.
    """
    msgs = _Messages()
    env = PusherReachEnv()
    plan = EpisodePlan(episodes, expert_frac, seed)  # who acts, as offline-rl collect and the recorder
    noise = np.random.default_rng(noise_seed)
    types = {t: TYPES[t] for t in topics}
    if "/pusher/command" in types:
        del types["/pusher/command"]
        if torque_commands:
            types["/effort_controller/commands"] = "std_msgs/msg/Float64MultiArray"
        elif source_tags:
            types["/pusher/command"] = TYPES["/pusher/command"]
        else:
            types.update({f"/pusher/command/{name}": TYPES["/pusher/command"] for name in ("expert", "random")})
    recv = [START_NS]

    def jitter(ns: int) -> int:
        return ns + (int(noise.integers(-jitter_ns, jitter_ns + 1)) if jitter_ns else 0)

    with BagWriter(path) as bag:
        for topic, msgtype in types.items():
            bag.add_topic(topic, msgtype)
        if labels:
            bag.add_topic("/episode_label", "std_msgs/msg/String")
            for at, success in labels:
                bag.write("/episode_label", at, encode_label_message(success))
        if estop:
            bag.add_topic("/estop", "std_msgs/msg/Bool")
            for at, value in estop:
                bag.write("/estop", at, bytes([0, 1, 0, 0, int(value), 0, 0, 0]))  # CDR LE header, the bool, padding

        def write(topic: str, data: bytes, at: int | None = None, droppable: bool = False) -> None:
            if topic not in types or (droppable and drop and noise.random() < drop):
                return
            copies = 2 if droppable and duplicates and noise.random() < duplicates else 1
            for _ in range(copies):
                recv[0] = max(recv[0] + 1000, at if at is not None else recv[0] + 1000)
                bag.write(topic, recv[0], data)

        def publish_state(ns: int) -> None:
            write("/pusher/target", msgs.point(jitter(ns), env.target), START_NS + ns)
            write("/pusher/fingertip", msgs.point(jitter(ns), env.fingertip), START_NS + ns)
            effort = np.ascontiguousarray(env.data.actuator_force[:ACT_DIM])
            write("/pusher/state", msgs.joint_state(jitter(ns), "", env.qpos, env.qvel, effort), START_NS + ns, True)

        tick = 0
        resend = None  # (topic, payload) of a command to send again after the next state
        for ep in range(episodes):
            obs = env.reset(seed=seed + ep)
            source = plan.source(ep)
            done = False
            while not done:
                ns = tick * TICK_NS
                publish_state(ns)
                if resend is not None:
                    write(*resend)
                    resend = None
                action = plan.action(ep, env.qpos, env.qvel, env.target[:2])
                if torque_commands:
                    torques = np.asarray(action, np.float64) * 0.5
                    write("/effort_controller/commands", msgs.float64_array(torques), START_NS + ns + 500_000, True)
                elif source_tags:
                    write("/pusher/command", msgs.joint_state(jitter(ns), SOURCE_NAMES[source], effort=action), None, True)
                else:
                    command = msgs.joint_state(jitter(ns), "", effort=action)
                    write(f"/pusher/command/{SOURCE_NAMES[source]}", command, None, True)
                    if republishes and noise.random() < republishes:
                        publish_state(ns)
                        write(f"/pusher/command/{SOURCE_NAMES[source]}", command)
                    if late_resends and noise.random() < late_resends:
                        resend = (f"/pusher/command/{SOURCE_NAMES[source]}", command)
                step = env.steps
                next_obs, reward, done, info = env.step(action)
                row = np.empty(TRANSITION_WIDTH, np.float32)
                for label, value in (("obs", obs), ("action", action), ("reward", reward), ("next_obs", next_obs),
                                     ("terminated", info["terminated"]), ("truncated", info["truncated"]),
                                     ("success", info["success"]), ("episode", ep), ("step", step), ("source", source)):
                    row[LAYOUT_SLICES[label]] = value
                write("/pusher/transition", encode_transition_rows(row[None])[0])
                obs = next_obs
                tick += 1
            if not sim_like:  # a real arm goes on publishing: its state after the last step,
                publish_state(tick * TICK_NS)
                tick += 5  # then a pause before the next episode's goal
            write("/pusher/reset", msgs.empty())
    assert tick >= episodes * MAX_STEPS


def pusher_task(**sections):
    """pusher_reach with some fields of its sections changed (``join={"stamps": "receive"}``)."""
    from offline_rl_core.task.spec import load_task, task_from_dict

    doc = load_task("pusher_reach").describe()
    for key, value in sections.items():
        doc[key] = {**doc[key], **value}
    return task_from_dict(doc)


def bag_messages(bag, task) -> list[tuple[str, str, bytes, int]]:
    """(topic, type, payload, receive time) of the task's topics, in the bag's order: what a
    learner subscribed to them takes off the wire."""
    from offline_rl_core.data.bag import open_bag
    from offline_rl_core.data.raw_topics import plan_for

    wanted = {r.topic for r in plan_for(task).roles}
    with open_bag(bag) as reader:
        conns = [c for c in reader.connections if c.topic in wanted]
        return [(c.topic, c.msgtype, bytes(raw), t) for c, t, raw in reader.messages(connections=conns)]
