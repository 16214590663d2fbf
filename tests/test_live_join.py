"""The live join: a recording's messages handed to ``LiveJoin`` one by one, as a learner takes
them off the wire, give the transitions the batch join (`offline-rl dataset`) builds from the
bag, row for row and bit for bit, in the same order, also when a lockstep sim waits for the
learner and when the topics' messages arrive interleaved differently from the bag."""

from __future__ import annotations

import numpy as np
import pytest

from offline_rl_core.data.raw_topics import LiveJoin, transitions_from_topics
from offline_rl_core.data.raw_topics.live import LiveSettings
from offline_rl_core.data.transitions import Transitions
from offline_rl_core.learners.success_classifier import (ClassifierConfig, SuccessClassifier, labelled_states,
                                                         train_classifier)
from offline_rl_core.task.spec import load_task

from raw_topic_bags import RAW_TOPICS, bag_messages, pusher_task, record_raw_bag

QUIET = LiveSettings().quiet


class Learner:
    """What the learner service does with a LiveJoin: take messages, poll, keep the steps."""

    def __init__(self, task, settings=None, judge=None, action_labels=False):
        self.live = LiveJoin(task, settings, judge, action_labels)
        self.parts, self.labels, self.steps, self.now = [], [], 0, 0.0

    def take(self, topic, msgtype, payload, recv):
        self.now += 1e-4
        assert self.live.add(topic, msgtype, payload, recv, self.now) is None
        self.poll()

    def poll(self, idle: bool = False, ended: bool = False):
        if idle:  # the learner had nothing to do for a while: nothing more was on the wire
            self.now += 2 * QUIET
        out = self.live.poll(self.now, ended=ended)
        self.steps += len(out)
        if len(out.transitions):
            self.parts.append(out.transitions)
            if out.labels is not None:
                self.labels.append(out.labels)

    def rows(self) -> np.ndarray:
        return Transitions.concatenate(self.parts).to_rows() if self.parts else np.zeros((0, 0), np.float32)


def bits(rows):
    return np.ascontiguousarray(rows, np.float32).view(np.uint32)


def assert_same_as_batch(learner: Learner, bag, task, judge=None):
    batch, report = transitions_from_topics(bag, task, judge=judge)
    learner.now += learner.live.settings.quiet_missing  # long enough that a lost command is taken as lost
    learner.poll(idle=True)
    before = learner.steps
    learner.poll(ended=True)  # the end of the session: nothing more comes
    assert learner.steps - before <= 1  # the last step: only the end says it has no next state
    live = learner.rows()
    assert live.shape == batch.to_rows().shape
    assert np.array_equal(bits(live), bits(batch.to_rows()))
    assert learner.steps == report.steps
    assert learner.live.counts.late == 0
    return batch, report


def test_a_paced_lockstep_session_joined_live_is_the_batch_join_of_its_bag(tmp_path):
    """The sim's lockstep stream (republished states and resent commands included) where the
    policy answers state n only once the learner holds n steps (the online stage's pacing):
    the live join never deadlocks, and its rows are the bag's batch join."""
    bag = tmp_path / "session.db3"
    record_raw_bag(bag, episodes=3, expert_frac=0.34, seed=4, sim_like=True, duplicates=0.1)
    task = load_task("pusher_reach")
    learner = Learner(task)
    states, pace = set(), 25
    for topic, msgtype, payload, recv in bag_messages(bag, task):
        if topic == "/pusher/state":
            states.add(recv)  # one per stamp in a sim bag; duplicates share the stamp's tick
        if topic.startswith("/pusher/command"):
            n = len({s // 20_000_000 for s in states}) - 1  # the state this command answers
            if n % pace == 0:
                for _ in range(3):  # the learner goes idle until it holds the steps before state n
                    if learner.steps >= n:
                        break
                    learner.poll(idle=True)
                assert learner.steps >= n, f"deadlock at state {n}: {learner.steps} steps"
        learner.take(topic, msgtype, payload, recv)
    assert_same_as_batch(learner, bag, task)


def test_a_success_classifier_judges_the_live_join_as_it_judges_the_batch(tmp_path):
    """Where no tracker says whether the arm succeeded, a classifier trained on a few labelled
    episodes judges each state (the learner's `success` parameter): the live rows are the
    batch join's with the same classifier, bit for bit, its disagreements with the task's
    success distance are counted alike, and only the reward and success flags differ from
    the distance's rows."""
    bag = tmp_path / "session.db3"
    record_raw_bag(bag, episodes=4, expert_frac=0.5, seed=4, sim_like=True)
    task = load_task("pusher_reach")
    ruled, _ = transitions_from_topics(bag, task)
    labels = {int(e): bool(ruled.success[ruled.episode == e][-1]) for e in np.unique(ruled.episode)}
    assert set(labels.values()) == {True, False}
    obs, success = labelled_states(ruled, labels, tail=5)
    # a few steps: a rough judge that disagrees with the distance somewhere, as a real one may
    judge = SuccessClassifier(train_classifier(obs, success, ClassifierConfig(steps=30), seed=0, task=task))
    learner = Learner(task, judge=judge)
    for message in bag_messages(bag, task):
        learner.take(*message)
    batch, report = assert_same_as_batch(learner, bag, task, judge=judge)
    assert learner.live.counts.as_dict()["judged"] == report.judged
    assert report.judged["successes"] == int(batch.success.sum())
    assert report.judged["rule_successes"] == int(ruled.success.sum())
    disagree = batch.success != ruled.success
    assert report.judged["false_successes"] + report.judged["missed"] == int(disagree.sum()) > 0
    for name in ("obs", "action", "next_obs", "episode", "step", "source"):
        assert np.array_equal(getattr(batch, name), getattr(ruled, name)), name
    bonus_moved = batch.reward != ruled.reward  # the success bonus, on another step or none
    assert bonus_moved.any()
    assert np.allclose(np.abs(batch.reward - ruled.reward)[bonus_moved], task.reward.success_bonus, atol=1e-5)


@pytest.mark.parametrize("seed", [0, 1])
def test_topics_interleaved_otherwise_than_in_the_bag_give_the_same_rows(tmp_path, seed):
    """A robot's log (states, goal and commands only; 10 % lost, stamps jittered, some sent
    twice) delivered with each message up to 15 ms late, each topic still in order: the same
    rows as the batch join."""
    bag = tmp_path / "robot.db3"
    record_raw_bag(bag, episodes=3, expert_frac=0.5, seed=3, sim_like=True, topics=RAW_TOPICS, drop=0.1,
                   jitter_ns=3_000_000, duplicates=0.05)
    task = pusher_task(join={"tolerance": 0.008, "period_tolerance": 0.008})
    rng = np.random.default_rng(seed)
    messages = bag_messages(bag, task)
    delivery = np.array([recv for *_, recv in messages], np.int64) + rng.integers(0, 15_000_000, len(messages))
    for topic in {m[0] for m in messages}:  # each topic in its own order
        idx = [i for i, m in enumerate(messages) if m[0] == topic]
        delivery[idx] = np.maximum.accumulate(delivery[idx])
    learner = Learner(task)
    for i in np.argsort(delivery, kind="stable"):
        learner.take(*messages[i])
    assert_same_as_batch(learner, bag, task)


def test_commands_without_a_header_joined_live_by_receive_time(tmp_path):
    bag = tmp_path / "torque.db3"
    record_raw_bag(bag, episodes=2, expert_frac=0.5, seed=5, sim_like=False, torque_commands=True)
    task = pusher_task(join={"stamps": "receive"})
    learner = Learner(task)
    for message in bag_messages(bag, task):
        learner.take(*message)
    assert_same_as_batch(learner, bag, task)


def test_republished_states_and_late_resends_joined_live_by_receive_time_as_in_the_batch(tmp_path):
    """Stamped states and commands joined by receive times, some states republished and
    their commands re-sent, some commands re-sent for a state the arm has left (received
    beside the next state): the live join keeps one of each, as the batch join does."""
    bag = tmp_path / "resends.db3"
    record_raw_bag(bag, episodes=2, expert_frac=0.5, seed=6, sim_like=True, late_resends=0.3, republishes=0.3)
    task = pusher_task(join={"stamps": "receive"})
    learner = Learner(task)
    for message in bag_messages(bag, task):
        learner.take(*message)
    assert_same_as_batch(learner, bag, task)
    _, report = transitions_from_topics(bag, task)
    assert report.commands["answering_an_earlier_state"] > 20 and report.transitions == 198


@pytest.mark.parametrize("which", [10, 60, -5])
def test_a_command_that_comes_after_the_next_state_and_a_short_silence_is_still_joined(tmp_path, which):
    """Joined by receive time, a command and the state it caused come from different writers,
    in no order between them: on a busy machine the command for state n can come after state
    n + 1 and a silence longer than the quiet rule's. The live join waits for it (a state is
    taken to have no command only after ``quiet_missing``), so no step is lost: a step lost
    there left a lockstep session paced on the steps waiting for it forever (CI, pusher7_reach)."""
    bag = tmp_path / "delayed.db3"
    record_raw_bag(bag, episodes=2, expert_frac=0.5, seed=7, sim_like=True)
    task = pusher_task(join={"stamps": "receive"})
    messages = bag_messages(bag, task)
    commands = [i for i, m in enumerate(messages) if m[0].startswith("/pusher/command")]
    late = commands[which]
    after = next(k for k in range(late, len(messages)) if messages[k][0] == "/pusher/state")
    learner = Learner(task)
    for i, message in enumerate(messages):
        if i == late:
            continue
        learner.take(*message)
        if i == after:
            learner.poll(idle=True)  # a silence longer than the quiet rule's, the command still on its way
            learner.take(*messages[late])
    assert_same_as_batch(learner, bag, task)


def test_a_state_whose_command_never_comes_is_stepless_after_quiet_missing(tmp_path):
    """A command lost on the way: after ``quiet_missing`` of silence the state is taken to
    have none (no step, as the batch join of the bag without it), and the steps after it come."""
    bag = tmp_path / "lost.db3"
    record_raw_bag(bag, episodes=1, expert_frac=1.0, seed=8, sim_like=True)
    task = pusher_task(join={"stamps": "receive"})
    messages = bag_messages(bag, task)
    lost = [i for i, m in enumerate(messages) if m[0].startswith("/pusher/command")][30]
    settings = LiveSettings()
    learner = Learner(task, settings)
    given = messages[:lost + 40]
    for i, message in enumerate(given):
        if i != lost:
            learner.take(*message)
    learner.poll(idle=True)
    before = sum(m[0].startswith("/pusher/command") for m in given[:lost])  # the steps before the lost one
    after = sum(m[0].startswith("/pusher/command") for m in given[lost + 1:])
    assert learner.steps <= before  # a short silence: the state may yet get its command
    learner.now += settings.quiet_missing
    learner.poll()
    # the lost command's state made no step and holds the steps after it back no longer (but
    # the latest state's, whose outcome only its next state settles)
    assert learner.steps >= before + after - 1


def test_a_message_that_does_not_fit_the_task_is_refused_and_counted(tmp_path):
    bag = tmp_path / "torque.db3"
    record_raw_bag(bag, episodes=1, expert_frac=1.0, seed=0, sim_like=False, torque_commands=True)
    task = pusher_task(join={"stamps": "receive"}, command={"joints": ["shoulder"], "scale": [0.5], "offset": [0.0]})
    live = LiveJoin(task)
    command = next(m for m in bag_messages(bag, task) if m[0] == "/effort_controller/commands")
    why = live.add(*command, now=0.0)
    assert why.reason == "wrong length" and "another length" in why and live.counts.refused == {"wrong length": 1}


@pytest.mark.parametrize("n", [3, 7])
def test_the_log_of_an_n_joint_velocity_arm_joined_live_is_its_batch_join(tmp_path, n):
    """The third arm (tests/velocity_arm.py): joint_states at 100 Hz in the broadcaster's
    shuffled order, velocity_controller/commands without a header (receive stamps), a
    JointState goal per episode, episodes ended by the time limit; taken message by message,
    the live join gives the batch join's rows."""
    import velocity_arm as va

    task_file = tmp_path / f"arm{n}.yaml"
    task_file.write_text(va.task_yaml(n))
    task = load_task(task_file)
    bag = tmp_path / f"arm{n}.db3"
    va.record_bag(bag, task, n, episodes=3, expert_frac=0.34, seed=2)
    learner = Learner(task)
    for message in bag_messages(bag, task):
        learner.take(*message)
    assert_same_as_batch(learner, bag, task)
    assert learner.rows().shape[0] > 0


def test_the_correctors_action_labels_are_joined_to_the_states_they_label(tmp_path):
    """``action_labels``: a label (``corrections/action_label``, stamped with its state) comes
    with the transition of the state it labels, clipped into [-1, 1] as a command is; a state
    without one has NaN; the transitions are the batch join's all the same; a label that comes
    after its step was handed out is counted late, not attached to another step."""
    from offline_rl_core.data.bag import typestore
    from offline_rl_core.data.raw_topics.spec import ACTION_LABEL_TOPIC

    from raw_topic_bags import _Messages

    bag = tmp_path / "session.db3"
    record_raw_bag(bag, episodes=2, expert_frac=0.5, seed=6, sim_like=True)
    task = load_task("pusher_reach")
    ts, msgs = typestore(), _Messages()
    learner = Learner(task, action_labels=True)
    topic, labelled, late = "/" + ACTION_LABEL_TOPIC, set(), None
    for name, msgtype, payload, recv in bag_messages(bag, task):
        if name.startswith("/pusher/command"):
            cmd = ts.deserialize_cdr(payload, msgtype)
            stamp = cmd.header.stamp.sec * 10**9 + cmd.header.stamp.nanosec
            if stamp not in labelled and len(labelled) % 3 != 2:  # every third state unlabelled
                labelled.add(stamp)
                label = msgs.joint_state(stamp, "", effort=1.5 * np.asarray(cmd.effort[::-1]))  # clipped
                if late is None and len(labelled) == 151:  # in the last episode, still in the window
                    late = label  # sent only once its step is out
                else:
                    learner.take(topic, "sensor_msgs/msg/JointState", label, recv - 1)
            else:
                labelled.add(stamp)
        learner.take(name, msgtype, payload, recv)
    learner.poll(idle=True)
    assert learner.live.add(topic, "sensor_msgs/msg/JointState", late, 0, learner.now) is None
    learner.now += learner.live.settings.quiet_missing
    learner.poll(idle=True)
    learner.poll(ended=True)
    rows = learner.rows()
    batch, _ = transitions_from_topics(bag, task)
    assert np.array_equal(bits(rows), bits(batch.to_rows()))
    got = np.concatenate(learner.labels)
    assert got.shape == batch.action.shape and learner.live.counts.late_topics == {topic: 1}
    given = np.isfinite(got).all(axis=1)
    assert np.isnan(got[~given]).all() and 0.5 * len(got) < given.sum() < len(got)
    want = np.clip(1.5 * batch.action[:, ::-1].astype(np.float64), -1, 1)
    assert np.allclose(got[given], want[given], atol=1e-6) and np.abs(got[given]).max() == 1.0
