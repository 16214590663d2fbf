"""The HIL-SERL stage over ROS: the learner node, the actor (policy node) and the rest as
real processes on a private DDS domain."""

import json
import os
import re
import signal
import subprocess
import sys

import numpy as np
import pytest
import torch

from ros_helpers import REPO, probe_node, require_ros, ros_env, spawn, task_bag_and_prior  # noqa: F401 - fixtures

pytestmark = pytest.mark.ros

STAGE = ["--env-steps", "300", "--publish-every", "25", "--eval-every", "150", "--eval-episodes", "4"]


@pytest.fixture(scope="module")
def prior(tmp_path_factory):
    require_ros()
    from offline_rl_core.data.bag import read_transitions
    from offline_rl_core.learners import TrainConfig, train
    from offline_rl_core.serving.checkpoint import save_checkpoint

    path = tmp_path_factory.mktemp("prior") / "policy.pt"
    result = train(read_transitions(REPO / "bags" / "mix.db3"), TrainConfig(algo="awac", steps=100), seed=0)
    save_checkpoint(path, result.checkpoint)
    return path


@pytest.fixture(scope="module")
def reference(prior):
    """The same stage in one process: what the ROS run must reproduce bit for bit."""
    from offline_rl_core.data.bag import read_transitions
    from offline_rl_core.learners.online import OnlineSettings
    from offline_rl_core.runs.online_loop import OnlineRunConfig, run_online
    from offline_rl_core.serving.checkpoint import load_checkpoint

    return run_online(read_transitions(REPO / "bags" / "mix.db3"), load_checkpoint(prior),
                      OnlineRunConfig(env_steps=300, seed=0, eval_every=150, eval_episodes=4,
                                      settings=OnlineSettings(publish_every=25)), log=lambda s: None)


def _hil_online(out, prior, *extra):
    return [sys.executable, "-m", "offline_rl_core", "hil", "--online", *STAGE, "--prior", str(prior),
            "--out", str(out), *extra]


def _assert_same_weights(path, reference):
    served = torch.load(path, weights_only=True)
    assert served["weights_version"] == reference["final_weights"]["weights_version"] == 12
    for key, value in reference["final_weights"]["policy_state"].items():
        assert torch.equal(served["policy_state"][key], value), key


@pytest.mark.slow
def test_the_stage_over_ros_reproduces_the_in_process_run(ros_env, tmp_path, prior, reference):
    out = tmp_path / "online"
    proc = subprocess.run(_hil_online(out, prior), env=ros_env, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["counts"]["steps"] == reference["counts"]["steps"] == 300
    assert summary["counts"]["human"] == reference["counts"]["human"] > 0  # the corrector's takeovers
    assert [p["successes"] for p in summary["curve"]] == [p["successes"] for p in reference["curve"]]
    _assert_same_weights(out / "learner" / "policy.pt", reference)
    # the curves in TensorBoard's event files: the stage's learning curve in DIR, the learner's versions in DIR/learner
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    stage, learner = EventAccumulator(str(out)), EventAccumulator(str(out / "learner"))
    stage.Reload()
    learner.Reload()
    assert [(e.step, e.value) for e in stage.Scalars("eval/success_rate")] == \
        [(p["env_steps"], pytest.approx(p["success"])) for p in summary["curve"]]
    assert learner.Scalars("online/weights_version")[-1].value == 12
    # the bag says which weights acted: every answer of the policy node is on policy/provenance
    from offline_rl_core.data.bag import read_transitions

    session = read_transitions(out / "session.db3")
    assert len(session) == 300 and set(np.unique(session.source)) == {2, 3}


@pytest.mark.slow
def test_a_killed_learner_restarts_and_the_session_ends_as_if_it_never_died(ros_env, tmp_path, prior, reference):
    out = tmp_path / "online"
    proc = subprocess.Popen(_hil_online(out, prior), env=ros_env, cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    log, killed = [], False
    try:
        for line in proc.stderr:
            log.append(line)
            if "learner pid" in line and not killed:
                pid = int(line.rsplit("learner pid", 1)[1].split()[0])
            shown = re.match(r"\s*(\d+)/300 environment steps", line)
            if not killed and shown and 100 <= int(shown.group(1)) < 250:  # mid-session, whichever line shows it
                os.kill(pid, signal.SIGKILL)  # the learner process the stage started, by its pid
                killed = True
        assert proc.wait(timeout=600) == 0, "".join(log[-40:])
    finally:
        proc.kill()
    assert killed, "".join(log)
    text = "".join(log)
    assert "the learner stopped" in text and "resumed" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["counts"]["learner_restarts"] == 1
    _assert_same_weights(out / "learner" / "policy.pt", reference)


def _provenance_versions(bag) -> list[int]:
    """The weights version of every answer a policy node recorded on policy/provenance."""
    from rosbags.typesys import Stores, get_typestore

    from offline_rl_core.data.bag.reader import open_bag, one_topic

    typestore = get_typestore(Stores.ROS2_HUMBLE)
    with open_bag(bag) as reader:
        topic = one_topic(reader, "/policy/provenance")
        connections = [c for c in reader.connections if c.topic == topic]
        return [json.loads(typestore.deserialize_cdr(bytes(raw), "std_msgs/msg/String").data)["weights_version"]
                for _, _, raw in reader.messages(connections=connections)]


@pytest.mark.slow
def test_two_actors_in_two_namespaces_feed_one_learner_and_act_on_its_weights(ros_env, tmp_path, prior):
    """--actors 2: two sims (/arm1, /arm2), each with its policy node, mux and corrector, and one
    learner. The learner trains on both actors' transitions, counted by namespace; each actor
    records only its own; both policy nodes act on the learner's new weights, paced to the
    version that holds about as many steps of each actor as they have taken."""
    from offline_rl_core.data.bag import read_transitions

    out = tmp_path / "online"
    cmd = [sys.executable, "-m", "offline_rl_core", "hil", "--online", "--actors", "2", "--env-steps", "400",
           "--publish-every", "25", "--eval-every", "100", "--eval-episodes", "2", "--prior", str(prior),
           "--out", str(out), "--logger", "none"]
    proc = subprocess.run(cmd, env=ros_env, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    progress = [json.loads(line) for line in (out / "learner" / "progress.jsonl").read_text().splitlines()]
    assert progress[-1]["trained_through"] == 400 and progress[-1]["weights_version"] == 16
    assert progress[-1]["received_from"] == {"/arm1": 200, "/arm2": 200}  # the learner's replay: both actors
    summary = json.loads((out / "summary.json").read_text())
    assert summary["counts"]["steps"] == 400 and [p["env_steps"] for p in summary["curve"]] == [0, 100, 200, 300, 400]
    assert {ns: a["trained_on"] for ns, a in summary["actors"].items()} == {"/arm1": 200, "/arm2": 200}
    sessions = {ns: read_transitions(out / ns / "session.db3") for ns in ("arm1", "arm2")}
    for ns, session in sessions.items():
        assert len(session) == 200 and len(np.unique(session.episode)) == 2, ns  # its own steps only
    # each its own block of the training resets: the arms start from other states
    assert not np.array_equal(sessions["arm1"].obs[0], sessions["arm2"].obs[0])
    for ns in ("arm1", "arm2"):
        versions = _provenance_versions(out / ns / "session.db3")
        assert versions == sorted(versions) and versions[-1] > versions[0], ns  # the learner's versions, newer on
        # state n waits for version n // 13 (publish_every / 2 actors): the last of 200 states acts on 15 or newer
        assert versions[-1] >= 15, (ns, versions[-20:])


@pytest.mark.slow
@pytest.mark.parametrize("judged", [False, True], ids=["success-distance", "classifier"])
def test_on_raw_topics_the_learner_trains_on_the_batch_join_of_the_sessions_recording(ros_env, tmp_path, prior,
                                                                                       judged):
    """The stage against an arm that publishes only standard topics (--from-topics): the
    learner joins the raw topics live, and its online buffer is, row for row and in order,
    what `offline-rl dataset` builds from the passive recorder's bag of the same session;
    the recording holds the raw topics and no transition. With a success classifier
    (--success: no tracker says whether the arm succeeded), the learner's successes and
    rewards are the classifier's, as `offline-rl dataset --success` builds them."""
    from offline_rl_core.data.bag import read_transitions
    from offline_rl_core.data.bag.info import bag_info
    from offline_rl_core.data.episode_labels import labels_from_success
    from offline_rl_core.data.raw_topics import transitions_from_topics
    from offline_rl_core.learners.data import MemberData
    from offline_rl_core.learners.success_classifier import (ClassifierConfig, labelled_states, load_classifier,
                                                             save_classifier, train_classifier)
    from offline_rl_core.task.spec import load_task

    out = tmp_path / "online"
    extra, judge = [], None
    if judged:
        task = load_task("pusher_reach")
        mix = read_transitions(REPO / "bags" / "mix.db3")
        obs, success = labelled_states(mix, labels_from_success(mix), tail=10)
        save_classifier(tmp_path / "cls.pt", train_classifier(obs, success, ClassifierConfig(steps=200), 0, task))
        extra, judge = ["--success", str(tmp_path / "cls.pt")], load_classifier(tmp_path / "cls.pt", task)
    cmd = [sys.executable, "-m", "offline_rl_core", "hil", "--online", "--env-steps", "200", "--publish-every", "25",
           "--eval-every", "100", "--eval-episodes", "2", "--prior", str(prior), "--out", str(out),
           "--task", "pusher_reach", "--from-topics", *extra]
    proc = subprocess.run(cmd, env=ros_env, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    topics = {t.name for t in bag_info(out / "session.db3").topics}
    assert "/pusher/transition" not in topics and {"/pusher/state", "/pusher/target", "/pusher/command/policy"} <= topics
    batch, report = transitions_from_topics(out / "session.db3", "pusher_reach", judge=judge)
    live = json.loads((out / "learner" / "live.json").read_text())["join"]
    # first what every later check rests on: no message came after a step it could change
    # was handed out (else the live rows may rightly differ from the bag's; its topic named)
    assert live["late"] == 0, live
    if judged:
        assert live["judged"] == report.judged and report.judged["judge"] == str(tmp_path / "cls.pt")
        assert report.judged["successes"] == int(batch.success.sum())
    else:
        assert "judged" not in live
    state = torch.load(out / "learner" / "learner_state.pt", weights_only=True)
    assert state["n_online"] == len(batch) == 198  # two episodes, each but its last step
    assert state["n_steps"] == report.steps - 1 == 199  # the session's last step: no later state closes it
    expected = MemberData.columns(batch)
    for name in ("obs", "action", "reward", "next_obs", "not_done", "human"):
        assert np.array_equal(state["online_rows"][name].numpy(), expected[name]), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["counts"]["steps"] == 198 and summary["counts"]["human"] == int(expected["human"].sum())
    # the curve ends on the learner's final weights, past the last snapshot (200 steps were 199 here)
    final = torch.load(out / "learner" / "policy.pt", weights_only=True)
    assert [p["env_steps"] for p in summary["curve"]] == [0, 100, final["trained_through"]]
    assert final["trained_through"] == 175
    # scored again from what the session kept, the curve is the same
    from offline_rl_core.pipelines.hil_online import rescore

    assert rescore(out)["curve"] == summary["curve"]


def test_the_learner_node_drops_bad_transitions_and_counts_them(spawn, tmp_path, prior):
    """Also under use_sim_time with no /clock (its work runs on the wall clock), and every
    weights version it publishes is signed with the session's key."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Float32MultiArray, String, UInt8MultiArray

    from offline_rl_core.serving.signing import load_verifier, make_session_keys
    from offline_rl_core.serving.weights import decode_weights

    from offline_rl_core.data.bag import write_transitions
    from offline_rl_core.data.collect import collect_transitions
    from offline_rl_core.data.transitions import TRANSITION_LAYOUT as LAYOUT

    data = collect_transitions(2, 0.5, 0)
    write_transitions(tmp_path / "offline.db3", data)
    keys = make_session_keys(tmp_path / "keys")
    learner = spawn([sys.executable, "-m", "pusher_learner.node", "--bag", str(tmp_path / "offline.db3"),
                     "--prior", str(prior), "--out", str(tmp_path / "learner"), "--publish-every", "2",
                     "--signing-key", str(keys.signing_key), "--ros-args", "-p", "use_sim_time:=true"], "learner")
    assert learner.wait_for_output("learning from", 60), learner.output()
    statuses, weights = [], []
    with probe_node() as node:
        node.create_subscription(String, "/learner/status", lambda m: statuses.append(json.loads(m.data)), 10)
        node.create_subscription(UInt8MultiArray, "/learner/weights", lambda m: weights.append(bytes(m.data)),
                                 QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                                            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        pub = node.create_publisher(Float32MultiArray, "/pusher/transition", 10)
        assert node.spin_until(lambda: pub.get_subscription_count() > 0, 30), learner.output()
        from std_msgs.msg import MultiArrayDimension

        def message(row, layout=LAYOUT):
            msg = Float32MultiArray(data=[float(v) for v in row])
            msg.layout.dim = [MultiArrayDimension(label=label, size=size, stride=size) for label, size in layout]
            return msg

        rows = data.to_rows()
        nan = rows[0].copy()
        nan[10] = np.nan  # the reward
        pub.publish(message(nan))
        pub.publish(message(rows[1][:20], layout=(("obs", 8), ("action", 2), ("reward", 10))))
        pub.publish(message(rows[2]))
        pub.publish(message(rows[3]))
        # the two good ones are trained on and a weights version is cut from them
        assert node.spin_until(lambda: statuses and statuses[-1]["received"] == 2
                               and sum(statuses[-1]["rejected"].values()) == 2
                               and statuses[-1]["weights_version"] == 1, 30), (statuses[-3:], learner.output())
        assert node.spin_until(lambda: len(weights) == 2, 30), len(weights)  # versions 0 and 1
    verifier = load_verifier(keys.public_key)
    assert [decode_weights(w, verifier)["weights_version"] for w in weights] == [0, 1]
    assert set(statuses[-1]["rejected"]) == {"non-finite", "bad layout"}
    assert "ignoring pusher/transition" in learner.output()


@pytest.mark.slow
def test_a_person_at_the_keyboard_takes_over_in_realtime(ros_env, tmp_path, prior):
    """End to end in a pseudo-terminal: the person's keys take over the arm in the realtime
    stage, and what they did lands in the session bag and in the learner's buffer as human."""
    import pty
    import threading
    import time

    out = tmp_path / "online"
    cmd = [sys.executable, "-m", "offline_rl_core", "hil", "--online", "--mode", "realtime", "--corrector", "keyboard",
           "--env-steps", "1000", "--publish-every", "25", "--eval-every", "500", "--eval-episodes", "4",
           "--prior", str(prior), "--out", str(out)]
    pid, fd = pty.fork()
    if pid == 0:  # the child: the stage, on the pseudo-terminal
        os.chdir(REPO)
        os.execve(cmd[0], cmd, ros_env)
    screen = []
    reader = threading.Thread(target=lambda: _read_all(fd, screen), daemon=True)
    reader.start()

    def shown(text, timeout):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in "".join(screen):
                return True
            time.sleep(0.05)
        return False

    def learner_progress(key):
        try:
            return json.loads((out / "learner" / "progress.jsonl").read_text().splitlines()[-1])[key]
        except (OSError, IndexError, ValueError, KeyError):
            return 0

    def human_steps():
        return learner_progress("human")

    try:
        assert shown("answering", 120), "".join(screen)[-3000:]  # the keyboard corrector is up
        # a takeover is a person's step after the policy's in one episode: the policy acts first
        deadline = time.monotonic() + 60
        while learner_progress("received") == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        os.write(fd, b"d")  # shoulder torque +1: the person takes over
        deadline = time.monotonic() + 60
        while human_steps() < 10 and time.monotonic() < deadline:  # the learner has their steps
            time.sleep(0.05)
        os.write(fd, b" ")  # hand back to the policy
        _, status = os.waitpid(pid, 0)
        pid = 0
        assert os.waitstatus_to_exitcode(status) == 0, "".join(screen)[-3000:]
    finally:
        if pid:
            os.kill(pid, signal.SIGINT)
            os.waitpid(pid, 0)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["counts"]["human"] >= 10 and summary["counts"]["takeovers"] >= 1
    state = torch.load(out / "learner" / "learner_state.pt", weights_only=True)
    assert float(state["online_rows"]["human"].sum()) >= 10  # the learner has the person's steps


def _read_all(fd, screen):
    while True:
        try:
            data = os.read(fd, 4096)
        except OSError:
            return
        if not data:
            return
        screen.append(data.decode(errors="replace"))


@pytest.fixture(scope="module")
def pusher7(tmp_path_factory):
    """A 4-episode pusher7_reach bag and a 50-step AWAC prior trained on it."""
    return task_bag_and_prior(tmp_path_factory, "pusher7_reach")


@pytest.mark.slow
def test_the_online_stage_runs_on_pusher7_reach(ros_env, tmp_path, pusher7):
    """`offline-rl hil --online --task pusher7_reach`: the sim hosts the 7-joint arm, the
    learner fine-tunes a prior of that task from the arm's steps over ROS (the transitions in
    the task's layout), and each point of the learning curve is scored on held-out rollouts
    of pusher7_reach's own env."""
    from offline_rl_core.data.bag import read_transitions
    from offline_rl_core.evaluation.rollouts import evaluate_policy
    from offline_rl_core.runs.online_loop import EVAL_SEED
    from offline_rl_core.serving.checkpoint import load_checkpoint
    from offline_rl_core.serving.policy import load_policy
    from offline_rl_core.task.spec import load_task

    task = load_task("pusher7_reach")
    bag, prior = pusher7
    out = tmp_path / "online"
    proc = subprocess.run([sys.executable, "-m", "offline_rl_core", "hil", "--online", "--task", "pusher7_reach",
                           "--bag", str(bag), "--prior", str(prior), "--env-steps", "200",
                           "--publish-every", "25", "--eval-every", "100", "--eval-episodes", "2", "--out", str(out)],
                          env=ros_env, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert [p["env_steps"] for p in summary["curve"]] == [0, 100, 200]
    final = load_checkpoint(out / "learner" / "policy.pt")
    assert final["task"]["digest"] == task.digest and (final["obs_dim"], final["act_dim"]) == (task.obs_dim, 7)
    # the curve's last point is the final weights scored on pusher7_reach's held-out resets
    snapshot = sorted((out / "learner" / "snapshots").glob("policy_*.pt"))[-1]
    ev = evaluate_policy(load_policy(snapshot, task), 2, EVAL_SEED, task=task)
    assert (ev["successes"], ev["mean_final_dist"]) == (summary["curve"][-1]["successes"],
                                                        summary["curve"][-1]["final_dist"])
    session = read_transitions(out / "session.db3")
    assert len(session) == 200 and session.layout.obs_dim == task.obs_dim and session.layout.act_dim == 7


@pytest.mark.slow
def test_on_pusher7_reach_raw_topics_the_learner_trains_on_the_arms_joined_topics(ros_env, tmp_path, pusher7):
    """`hil --online --task pusher7_reach --from-topics`: the 7-joint arm as a ros2_control
    arm has it (joint_states, velocity_controller/commands as Float64MultiArray without a
    header, the goal; no pusher/transition in the session). Its commands are joined by
    receive times, so the learner and the recorder stamp each message with the sim time of
    its publication: in lockstep the session runs to its end (each paced weights version
    needs the steps before it) and the learner's rows are pusher7_reach's, each command
    joined with the state it answered."""
    from offline_rl_core.data.bag.info import bag_info
    from offline_rl_core.serving.checkpoint import load_checkpoint
    from offline_rl_core.task.spec import load_task

    task = load_task("pusher7_reach")
    bag, prior = pusher7
    out = tmp_path / "online"
    proc = subprocess.run([sys.executable, "-m", "offline_rl_core", "hil", "--online", "--task", "pusher7_reach",
                           "--from-topics", "--bag", str(bag), "--prior", str(prior), "--env-steps", "200",
                           "--publish-every", "25", "--eval-every", "200", "--eval-episodes", "1", "--logger", "none",
                           "--out", str(out)], env=ros_env, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    topics = {t.name for t in bag_info(out / "session.db3").topics}
    assert "/pusher/transition" not in topics
    # the arm's own state and goal; its commands come through the mux (the policy's or the
    # person's), never from the policy node straight to the controller, which would bypass it
    assert {"/" + task.state.topic, "/" + task.goal.topic, "/pusher/command/policy"} <= topics, topics
    assert "/" + task.command.topic not in topics, topics
    state = torch.load(out / "learner" / "learner_state.pt", weights_only=True)
    # every step; the session's last (no later state comes) only if the learner, idle, took
    # the arm's silence as its end before it was stopped
    assert state["n_steps"] in (199, 200)
    # what was trained on live is what `offline-rl dataset --from-topics` builds from the bag
    from offline_rl_core.data.raw_topics import transitions_from_topics
    from offline_rl_core.learners.data import MemberData

    batch, _ = transitions_from_topics(out / "session.db3", "pusher7_reach")
    expected = MemberData.columns(batch)
    for name in ("obs", "action", "reward", "next_obs", "not_done", "human"):
        got = state["online_rows"][name].numpy()
        assert np.array_equal(got, expected[name][:len(got)]), name
    assert len(batch) - state["n_online"] in (0, 1)  # the session's last step, if the learner had not got it
    # two episodes, each but its last step: a command the mux re-sent for a state the arm had
    # left (answering a republished copy late) names that state in its header, and is not joined
    assert state["n_online"] == 198
    assert state["online_rows"]["obs"].shape == (198, task.obs_dim) and state["online_rows"]["action"].shape == (198, 7)
    rows = state["online_rows"]
    live = json.loads((out / "learner" / "live.json").read_text())
    assert live["transitions"] == 198 and live["steps"] in (199, 200), live
    # each step's next state is the next step's state but at the episode's end (the sim
    # resets): every command was joined with the state it answered, once
    jumps = torch.nonzero((rows["next_obs"][:-1] != rows["obs"][1:]).any(dim=1)).flatten().tolist()
    assert jumps == [98], jumps
    final = load_checkpoint(out / "learner" / "policy.pt")
    assert final["task"]["digest"] == task.digest and final["weights_version"] == 7


@pytest.fixture(scope="module")
def push(tmp_path_factory):
    """A 4-episode pusher_push bag and a 50-step AWAC prior trained on it."""
    return task_bag_and_prior(tmp_path_factory, "pusher_push")


@pytest.mark.slow
def test_on_the_push_task_the_scripted_corrector_takes_over_and_labels_every_state_it_leaves(
        ros_env, tmp_path, push):
    """`hil --online --task pusher_push --from-topics --action-labels`: the corrector node hears
    the puck from its tracker's topic, takes over with the push expert, and labels every other
    state with the action it would take (corrections/action_label, in the session bag); the
    learner joins each label to its state, so every transition it trains on is imitable (a
    takeover or a labelled state), its labels the corrector's, its actions the arm's."""
    from offline_rl_core.data.bag import open_bag, typestore
    from offline_rl_core.data.raw_topics import transitions_from_topics
    from offline_rl_core.data.transitions import SOURCE_HUMAN, SOURCE_POLICY

    bag, prior = push
    out = tmp_path / "online"
    proc = subprocess.run([sys.executable, "-m", "offline_rl_core", "hil", "--online", "--task", "pusher_push",
                           "--from-topics", "--action-labels", "--bag", str(bag), "--prior", str(prior),
                           "--env-steps", "300", "--publish-every", "25", "--eval-every", "150", "--eval-episodes",
                           "1", "--patience", "1", "--hold-steps", "10", "--logger", "none", "--out", str(out)],
                          env=ros_env, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    ts = typestore()
    with open_bag(out / "session.db3") as reader:
        conns = [c for c in reader.connections if c.topic == "/corrections/action_label"]
        sent = [ts.deserialize_cdr(raw, c.msgtype) for c, _, raw in reader.messages(connections=conns)]
    state = torch.load(out / "learner" / "learner_state.pt", weights_only=True)
    rows = state["online_rows"]
    batch, _ = transitions_from_topics(out / "session.db3", "pusher_push")
    policy = np.flatnonzero(batch.source[:state["n_online"]] == SOURCE_POLICY)
    human = np.flatnonzero(batch.source[:state["n_online"]] == SOURCE_HUMAN)
    assert len(policy) and len(human)  # the corrector took over, and left states to the policy
    assert np.array_equal(rows["action"].numpy(), batch.action[:state["n_online"]])  # the critic's: the arm's
    assert rows["human"].numpy().all()  # every transition a takeover or a labelled state
    assert state["n_labelled"] == len(policy) and state["n_human"] == len(human)
    labels = {tuple(np.clip(np.asarray(m.effort), -1, 1).astype(np.float32)) for m in sent}
    assert all(tuple(row) in labels for row in rows["label"].numpy()[policy])
    assert np.array_equal(rows["label"].numpy()[human], rows["action"].numpy()[human])
    assert len(policy) <= len(sent) <= len(policy) + 2  # each episode's last state: labelled, no transition
    summary = json.loads((out / "summary.json").read_text())
    assert summary["counts"]["labelled"] == len(policy) and summary["config"]["action_labels"] is True


@pytest.mark.slow
def test_over_ros_the_classifiers_success_ends_the_arms_episode_and_the_learners(ros_env, tmp_path, push):
    """`hil --online --from-topics --success CLS --end-on-success` on pusher_push: the policy
    node labels each state the classifier judges a success on episode_label, the sim ends the
    episode at its next step, and the learner's episodes end at the first judged success
    (terminated; the step the label let through is left out), as `offline-rl dataset`
    builds them from the session's bag; the sim runs --env-steps steps, not whole episodes.
    Here the classifier judges every state a success (its threshold 0): every episode ends
    within a few steps, and the learner keeps one transition of each (the arm's last step of
    an episode closes on no published state: no transition, as at any episode's end)."""
    from offline_rl_core.data.bag import read_transitions
    from offline_rl_core.data.bag.info import bag_info
    from offline_rl_core.data.episode_labels import labels_from_success
    from offline_rl_core.data.raw_topics import transitions_from_topics
    from offline_rl_core.learners.data import MemberData
    from offline_rl_core.learners.success_classifier import (ClassifierConfig, labelled_states, load_classifier,
                                                             save_classifier, train_classifier)
    from offline_rl_core.task.spec import load_task

    task = load_task("pusher_push")
    bag, prior = push
    data = read_transitions(bag)
    obs, success = labelled_states(data, labels_from_success(data), tail=10)
    contents = train_classifier(obs, success, ClassifierConfig(steps=50), 0, task)
    contents["config"]["threshold"] = 0.0  # every state a success
    save_classifier(tmp_path / "always.pt", contents)
    judge = load_classifier(tmp_path / "always.pt", task)
    out = tmp_path / "online"
    proc = subprocess.run([sys.executable, "-m", "offline_rl_core", "hil", "--online", "--task", "pusher_push",
                           "--from-topics", "--success", str(tmp_path / "always.pt"), "--end-on-success",
                           "--bag", str(bag), "--prior", str(prior), "--env-steps", "90", "--publish-every", "15",
                           "--eval-every", "45", "--eval-episodes", "1", "--corrector", "none", "--logger", "none",
                           "--out", str(out)], env=ros_env, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    sim = json.loads((out / "sim.json").read_text())
    # every episode the sim ran was ended by the classifier's label within a few steps of its
    # start (the label of state s ends the step after the one its answer lets through, or that
    # one), but the last, which the budget may cut first
    assert sim["labelled"] >= sim["episodes"] - 1 and 90 // 4 <= sim["episodes"] <= 90
    recorded = {t.name: t.count for t in bag_info(out / "session.db3").topics}
    assert recorded["/episode_label"] >= sim["labelled"]  # the session bag keeps the policy node's labels
    batch, report = transitions_from_topics(out / "session.db3", task, judge=judge, end_on_success=True)
    assert batch.terminated.all() and np.array_equal(batch.step, np.zeros(len(batch)))  # each episode's first step
    # one transition an episode at most: an episode the label ended at its first step closes on
    # no published state, so it makes none (the label can overtake the mux's first command)
    assert len(np.unique(batch.episode)) == len(batch) and 0 < len(batch) <= sim["episodes"]
    # every step the arm took counts toward the budget, those left out too (all but the last: no state closes it)
    assert json.loads((out / "learner" / "live.json").read_text())["steps"] == 89
    # the learner trained on those rows, in order: its episodes ended where the arm's did
    state = torch.load(out / "learner" / "learner_state.pt", weights_only=True)
    expected = MemberData.columns(batch)
    for name in ("obs", "action", "reward", "next_obs", "not_done"):
        assert np.array_equal(state["online_rows"][name].numpy(), expected[name][:state["n_online"]]), name
    assert not state["online_rows"]["not_done"].numpy().any()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["config"]["end_on_success"] is True and summary["curve"][0]["env_steps"] == 0
