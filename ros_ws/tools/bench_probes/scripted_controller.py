"""A user's scripted controller for a task's arm, over its raw topics only (a bench probe).

It stands in for whatever drives a real ros2_control arm while someone records it: it
hears the task's state (sensor_msgs/JointState), goal and tracked points with a topic (a
tracker's puck) on their topics, and answers
each state on the controller's command topic (std_msgs/Float64MultiArray in the
controller's joint order, or a JointState command, as the task says), with the actions
of ``offline_rl_core.data.collect.EpisodePlan``: the task's scripted expert for the first
``round(expert_frac * episodes)`` episodes, uniform random actions after. Against a
lockstep sim started with reset seed ``seed`` it so drives the episodes ``offline-rl
collect --task TASK --episodes N --expert-frac F --seed S`` rolls out in one process.

    python scripted_controller.py TASK EPISODES EXPERT_FRAC SEED [SUBSCRIBERS [PACE_S]]

A new episode is a new goal (the sim draws one per reset). The first command waits until
SUBSCRIBERS readers (default 1: the sim; 2 with a recorder) have matched the command topic
and all but the sim, besides this node, the state topic, and the sim has republished its
first state twice more (to every reader matched by then), so a recorder started beside it
misses nothing. A state heard again with the stamp already answered is the sim republishing it
while our answer is in flight: it is not answered twice (a headerless command answering a
republished state would be taken for the next state's). PACE_S (default 0): at least
this many seconds of wall time between two commands, so that a recorder has written each
message before the next comes (a recorder on sim time stamps what it has not yet taken
when a newer /clock arrives with that newer time). Ends after the last episode's
time limit (an episode ended early, on success, leaves that to whoever started it: stop it
by its pid once the sim has run its episodes); its last stdout line is JSON (states
answered, episodes, expert episodes).
"""

import json
import sys
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PointStamped, PoseStamped
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from offline_rl_core.benchmarks.ros_procs import wait_until
from offline_rl_core.data.collect import EpisodePlan
from offline_rl_core.nodes.joint_messages import command_from_action
from offline_rl_core.nodes.observation import ObservationBuilder, kinematics_model
from offline_rl_core.task.spec import JOINT_STATE, POSE_STAMPED, load_task


def stamp_ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def drive(task_name: str, episodes: int, expert_frac: float, seed: int, subscribers: int, pace_s: float) -> dict:
    task = load_task(task_name)
    plan = EpisodePlan(episodes, expert_frac, seed, task)
    reader = ObservationBuilder(task, kinematics_model(task))
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("scripted_controller", context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    goals: dict[int, np.ndarray] = {}
    states: dict[int, tuple] = {}
    progress = {"answered": 0, "episode": -1, "last_goal": None, "last_stamp": None, "steps": 0, "sent_at": 0.0}

    def on_goal(msg):
        if task.goal.type == JOINT_STATE:
            goal, bad = reader.goal_from_joints(msg.name, msg.position)
        else:
            p = msg.pose.position if task.goal.type == POSE_STAMPED else msg.point
            goal, bad = reader.goal_from_point(p.x, p.y, p.z)
        if goal is not None:
            goals[stamp_ns(msg.header.stamp)] = goal

    # tracked points with a topic (an object a tracker publishes), by the state's stamp
    tracked = [p for p in task.points if p.topic]
    tracked_at: dict[str, dict[int, np.ndarray]] = {p.name: {} for p in tracked}

    def on_point(msg, name):
        p = msg.pose.position if isinstance(msg, PoseStamped) else msg.point
        vector, bad = reader.point(name, p.x, p.y, p.z)
        if vector is not None:
            tracked_at[name][stamp_ns(msg.header.stamp)] = vector

    for p in tracked:
        node.create_subscription(PoseStamped if p.type == POSE_STAMPED else PointStamped, p.topic,
                                 lambda m, name=p.name: on_point(m, name), 100)

    heard: dict[int, int] = {}  # copies of each state stamp heard

    def on_state(msg):
        key = stamp_ns(msg.header.stamp)
        heard[key] = heard.get(key, 0) + 1
        states[key] = (list(msg.name), list(msg.position), list(msg.velocity))

    goal_type = {JOINT_STATE: JointState, POSE_STAMPED: PoseStamped}.get(task.goal.type, PointStamped)
    node.create_subscription(goal_type, task.goal.topic, on_goal, 100)
    node.create_subscription(JointState, task.state.topic, on_state, 100)
    joint_command = task.command.type == JOINT_STATE
    pub = node.create_publisher(JointState if joint_command else Float64MultiArray, task.command.topic, 100)
    spin = lambda t: executor.spin_once(timeout_sec=t)  # noqa: E731

    def answer(stamp: int) -> None:
        (names, position, velocity), goal = states.pop(stamp), goals.pop(stamp)
        heard_points = {name: by_stamp.pop(stamp) for name, by_stamp in tracked_at.items()}
        joints, bad = reader.state(names, position, velocity)
        if joints is None:
            raise RuntimeError(f"a state the task cannot read: {bad}")
        positions, velocities = joints
        if progress["last_goal"] is None or not np.array_equal(goal, progress["last_goal"]):
            progress["episode"] += 1  # the sim drew a new goal: a reset
            progress["last_goal"] = goal
            progress["steps"] = 0
        episode = progress["episode"]
        if episode >= episodes:
            return
        vectors = reader.vectors(positions, goal, heard_points)
        points = {p.name: vectors[p.name] for p in task.points}
        action = plan.action(episode, positions, velocities, goal, points if episode < plan.n_expert else None)
        values = [float(v) for v in command_from_action(task.command, action)]
        if joint_command:
            msg = JointState(name=list(task.command.joints))
            setattr(msg, task.command.interface, values)
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        else:
            msg = Float64MultiArray(data=values)
        wait = progress["sent_at"] + pace_s - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        pub.publish(msg)
        progress["sent_at"] = time.monotonic()
        progress["answered"] += 1
        progress["steps"] += 1
        progress["last_stamp"] = stamp

    start = time.monotonic()
    try:
        if not wait_until(lambda: pub.get_subscription_count() >= subscribers
                          and node.count_subscribers(task.state.topic) >= subscribers, 60.0, spin):
            raise RuntimeError(f"{task.command.topic} never had {subscribers} readers")
        # the readers exist; the sim's writers may match them later: wait for the sim to
        # republish its first state twice more, to every reader matched by then
        if not wait_until(lambda: max(heard.values(), default=0) >= 3, 60.0, spin):
            raise RuntimeError(f"the sim did not republish its first state on {task.state.topic}")
        while True:
            spin(1.0)
            for stamp in sorted(states):
                if progress["last_stamp"] is not None and stamp <= progress["last_stamp"]:
                    del states[stamp]  # republished while our answer was in flight
                elif stamp in goals and all(stamp in by_stamp for by_stamp in tracked_at.values()):
                    answer(stamp)
            if progress["episode"] == episodes - 1 and progress["steps"] >= task.episodes.max_steps:
                # the last episode's last step: no later state comes; the command must reach
                # the sim before this node goes, so wait for the sim to end
                wait_until(lambda: node.count_publishers(task.state.topic) == 0, 30.0, spin)
                break
            for by_stamp in (goals, *tracked_at.values()):
                for old in [s for s in by_stamp if progress["last_stamp"] is not None and s <= progress["last_stamp"]]:
                    del by_stamp[old]
    except KeyboardInterrupt:  # stopped by whoever started it (the sim has run its episodes)
        pass
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    return {"answered": progress["answered"], "episodes": progress["episode"] + 1, "expert_episodes": plan.n_expert,
            "wall_s": round(time.monotonic() - start, 1)}


def main(argv: list) -> int:
    if len(argv) not in (4, 5, 6):
        print(__doc__, file=sys.stderr)
        return 2
    subscribers = int(argv[4]) if len(argv) >= 5 else 1
    pace_s = float(argv[5]) if len(argv) == 6 else 0.0
    print(json.dumps(drive(argv[0], int(argv[1]), float(argv[2]), int(argv[3]), subscribers, pace_s)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
