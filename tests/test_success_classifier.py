"""Success without the simulator: episode labels in a bag, a success classifier trained from
labelled episodes (`offline-rl classifier`), and the online stage judging success by it."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from offline_rl_core.common.errors import UserError
from offline_rl_core.data.bag import read_transitions
from offline_rl_core.data.bag.writer import write_transitions
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.data.episode_labels import episode_labels, labels_from_success, parse_label
from offline_rl_core.learners.success_classifier import ClassifierConfig, load_classifier
from offline_rl_core.serving.checkpoint import save_checkpoint
from offline_rl_core.runs.classifier_run import score_on_bags, train_from_bags
from offline_rl_core.task.spec import load_task

PUSH = load_task("pusher_push")


def offline_rl(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "offline_rl_core.commands.cli", *args], capture_output=True,
                          text=True, timeout=300)


@pytest.fixture(scope="module")
def push_data():
    """Three expert episodes (they end on the goal) and three random ones (they do not): resets
    4.., where the expert pushes each puck home (it misses 3 of the 100 held-out resets)."""
    return collect_transitions(6, 0.5, 4, task=PUSH)


@pytest.fixture(scope="module")
def labelled_bag(push_data, tmp_path_factory):
    """The push episodes in a bag with a person's labels: the simulator's word, but episode 1
    labelled a failure (a person may judge otherwise than the simulator)."""
    labels = {**labels_from_success(push_data), 1: False}
    path = tmp_path_factory.mktemp("labels") / "push.db3"
    write_transitions(path, push_data, task=PUSH, labels=labels)
    return path, labels


def test_the_simulators_labels_are_each_episodes_success_at_its_end(push_data):
    assert labels_from_success(push_data) == {0: True, 1: True, 2: True, 3: False, 4: False, 5: False}


def test_labels_are_read_back_from_the_bag_by_episode(labelled_bag):
    path, labels = labelled_bag
    assert episode_labels(path) == labels


def test_a_label_without_an_episode_is_of_the_episode_before_it(push_data, tmp_path):
    labels = {0: True, 3: False, 5: True}
    write_transitions(tmp_path / "b.db3", push_data, task=PUSH, labels=labels, label_episodes=False)
    assert episode_labels(tmp_path / "b.db3") == labels


def test_a_bag_without_labels_has_none(push_data, tmp_path):
    write_transitions(tmp_path / "b.db3", push_data, task=PUSH)
    assert episode_labels(tmp_path / "b.db3") == {}


@pytest.mark.parametrize("text, says", [
    ("yes", "a label is a JSON object"),
    ('{"label": "maybe"}', "field label: expected success or failure"),
    ('{"label": "success", "episode": -1}', "field episode: expected an episode number >= 0"),
    ('{"label": "success", "episode": true}', "field episode"),
])
def test_a_bad_label_is_one_line_naming_the_topic_and_field(text, says):
    with pytest.raises(UserError, match=says) as err:
        parse_label(text, "b.db3: /episode_label")
    assert str(err.value).startswith("b.db3: /episode_label") and "\n" not in str(err.value)


def test_a_classifier_learns_the_labels_and_is_the_same_for_a_seed(labelled_bag, tmp_path):
    path, labels = labelled_bag
    cfg = ClassifierConfig(steps=300)
    first = train_from_bags([str(path)], tmp_path / "a.pt", cfg, seed=0)
    second = train_from_bags([str(path)], tmp_path / "b.pt", cfg, seed=0)
    assert first["trained_on"]["labels"] == ["topic"]  # the person's, not the simulator's
    assert first["trained_on"]["episodes"] == len(labels)
    assert first["trained_on"]["success_episodes"] == sum(labels.values())
    for name, value in first["state"].items():
        assert np.array_equal(value.numpy(), second["state"][name].numpy()), name
    scores = score_on_bags(load_classifier(tmp_path / "a.pt", PUSH), [str(path)])
    assert (scores["episodes"], scores["successes"], scores["failures"]) == (6, 2, 4)
    assert scores["false_positives"] + scores["false_negatives"] <= 1  # on its own training episodes


def test_a_classifier_of_one_task_is_refused_by_another(labelled_bag, tmp_path):
    train_from_bags([str(labelled_bag[0])], tmp_path / "c.pt", ClassifierConfig(steps=10), seed=0)
    with pytest.raises(UserError, match="judges task pusher_push"):
        load_classifier(tmp_path / "c.pt", load_task("pusher_reach"))
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    with pytest.raises(UserError, match="junk.pt: not a readable"):
        load_classifier(tmp_path / "junk.pt")
    save_checkpoint(tmp_path / "other.pt", {"format": "something else"})
    with pytest.raises(UserError, match="other.pt: not a success classifier"):
        load_classifier(tmp_path / "other.pt")


def test_the_first_n_successes_and_failures_are_kept_and_too_few_are_refused(labelled_bag, tmp_path):
    path = str(labelled_bag[0])
    contents = train_from_bags([path], tmp_path / "d.pt", ClassifierConfig(steps=10), seed=0, successes=1,
                               failures=2)
    assert (contents["trained_on"]["episodes"], contents["trained_on"]["success_episodes"]) == (3, 1)
    with pytest.raises(UserError, match="too few labelled episodes: 1 more successes"):
        train_from_bags([path], tmp_path / "e.pt", ClassifierConfig(steps=10), seed=0, successes=3)


def test_classifier_train_and_eval_from_the_command_line(labelled_bag, tmp_path):
    path = str(labelled_bag[0])
    out = tmp_path / "cls.pt"
    train = offline_rl("classifier", "train", "--bag", path, "--out", str(out), "--steps", "200")
    assert train.returncode == 0, train.stderr
    assert json.loads(train.stdout)["success_episodes"] == 2
    rates = tmp_path / "rates.json"
    ev = offline_rl("classifier", "eval", "--classifier", str(out), "--bag", path, "--json", str(rates))
    assert ev.returncode == 0, ev.stderr
    written = json.loads(rates.read_text())
    assert written["false_positive_rate"] == json.loads(ev.stdout)["false_positive_rate"]
    bad = offline_rl("classifier", "train", "--bag", path, "--out", str(tmp_path / "x.pt"), "--threshold", "1.5")
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0 and "--threshold" in bad.stderr
    topic = offline_rl("classifier", "train", "--bag", str(tmp_path / "none.db3"), "--out", str(tmp_path / "y.pt"))
    assert topic.returncode == 2 and "none.db3" in topic.stderr


@pytest.mark.slow
def test_the_online_stage_takes_its_reward_and_episode_end_from_the_classifier(labelled_bag, tmp_path):
    from offline_rl_core.learners.config import TrainConfig
    from offline_rl_core.learners.online import OnlineSettings
    from offline_rl_core.runs.online_loop import OnlineRunConfig, rescore, run_online
    from offline_rl_core.task.envs import make_env

    path = str(labelled_bag[0])
    train_from_bags([path], tmp_path / "cls.pt", ClassifierConfig(steps=300), seed=0)
    judge = load_classifier(tmp_path / "cls.pt", PUSH)

    # each step's success is the classifier's judgement of the state reached, its reward the
    # task's with that success, and a judged success ends the episode
    env = make_env(PUSH, terminate_on_success=False)
    env.reset(3)
    for _ in range(5):
        next_obs, _, _, truth = env.step(np.zeros(PUSH.act_dim, np.float32))
        reward, info, judged = rescore(PUSH, env, next_obs, False, judge, True)
        assert judged == bool(judge.success(next_obs[None])[0]) == info["success"]
        assert info["terminated"] == judged
        _, sim_info, _ = rescore(PUSH, env, next_obs, False, None, False)
        assert sim_info["success"] == truth["success"] and not sim_info["terminated"]
        sim_reward = rescore(PUSH, env, next_obs, False, None, False)[0]
        # the same distances; only the success bonus follows the judge
        assert reward - sim_reward == pytest.approx(PUSH.reward.success_bonus * (judged - truth["success"]))

    offline = read_transitions(path)
    cfg = OnlineRunConfig(env_steps=120, seed=0, eval_every=120, eval_episodes=1, task="pusher_push",
                          success=str(tmp_path / "cls.pt"), end_on_success=True,
                          settings=OnlineSettings(utd=1, publish_every=20), train=TrainConfig(algo="sac"))
    run = run_online(offline, None, cfg, log=lambda s: None)
    counts = run["counts"]
    assert counts["steps"] == 120
    assert counts["false_ends"] <= counts["ended_early"] <= counts["episodes"]
    assert counts["judged_successes"] >= counts["ended_early"]
    assert run["config"]["success"] == str(tmp_path / "cls.pt") and run["config"]["task"] == "pusher_push"
    assert run["curve"][-1]["env_steps"] == 120
    with pytest.raises(UserError, match="judges task pusher_push"):
        run_online(read_transitions(path), None, replace(cfg, task="pusher_reach"), log=lambda s: None)


def test_hil_takes_the_classifier_in_process_or_on_raw_topics_only(tmp_path):
    over_ros = offline_rl("hil", "--online", "--success", "c.pt", "--out", str(tmp_path / "a"))
    assert over_ros.returncode == 2 and "--success: over ROS only with --from-topics" in over_ros.stderr
    ends = offline_rl("hil", "--online", "--end-on-success", "--out", str(tmp_path / "d"))
    assert ends.returncode == 2 and "--end-on-success: over ROS only with --from-topics" in ends.stderr
    offline_rounds = offline_rl("hil", "--success", "c.pt", "--out", str(tmp_path / "b"))
    assert offline_rounds.returncode == 2 and "--success: only with --online" in offline_rounds.stderr
    missing = offline_rl("hil", "--online", "--in-process", "--success", str(tmp_path / "none.pt"),
                         "--out", str(tmp_path / "c"))
    assert missing.returncode == 2 and "none.pt: no such classifier file" in missing.stderr


def test_dataset_from_topics_takes_its_success_from_a_classifier(tmp_path):
    """`offline-rl dataset --success FILE`: the join's successes are the classifier's, its
    report counts them against the task's success distance; another task's classifier is
    one line, and nothing is written."""
    from offline_rl_core.data.raw_topics import transitions_from_topics
    from offline_rl_core.learners.success_classifier import labelled_states, save_classifier, train_classifier
    from offline_rl_core.task.spec import load_task

    from raw_topic_bags import record_raw_bag

    reach = load_task("pusher_reach")
    raw = tmp_path / "raw.db3"
    record_raw_bag(raw, episodes=4, expert_frac=0.5, seed=4, sim_like=True)
    ruled, _ = transitions_from_topics(raw, reach)
    labels = {int(e): bool(ruled.success[ruled.episode == e][-1]) for e in np.unique(ruled.episode)}
    obs, success = labelled_states(ruled, labels, tail=5)
    save_classifier(tmp_path / "reach.pt", train_classifier(obs, success, ClassifierConfig(steps=30), 0, reach))
    report = tmp_path / "report.json"
    built = offline_rl("dataset", str(raw), str(tmp_path / "judged.db3"), "--success", str(tmp_path / "reach.pt"),
                       "--report", str(report))
    assert built.returncode == 0, built.stderr
    judged = json.loads(report.read_text())["judged"]
    assert judged["judge"] == str(tmp_path / "reach.pt") and "judged by" in built.stdout
    assert judged["successes"] == int(read_transitions(tmp_path / "judged.db3").success.sum())
    assert judged["rule_successes"] == int(ruled.success.sum())

    push = tmp_path / "push.pt"
    save_classifier(push, train_classifier(np.random.default_rng(0).normal(size=(20, PUSH.obs_dim)),
                                           np.arange(20) % 2 == 0, ClassifierConfig(steps=5), 0, PUSH))
    refused = offline_rl("dataset", str(raw), str(tmp_path / "out.db3"), "--success", str(push))
    assert refused.returncode == 2 and refused.stderr.strip().count("\n") == 0
    assert "push.pt" in refused.stderr and "judges task pusher_push" in refused.stderr
    assert not (tmp_path / "out.db3").exists()


def test_head_states_of_a_success_are_failures_and_never_its_tail(push_data):
    from offline_rl_core.learners.success_classifier import labelled_states

    labels = {0: True, 3: False}
    obs, success = labelled_states(push_data, labels, tail=10, head=40)
    steps = {e: int((push_data.episode == e).sum()) for e in labels}
    assert len(obs) == 40 + 10 + steps[3]
    assert success.tolist() == [False] * 40 + [True] * 10 + [False] * steps[3]
    first = push_data.next_obs[(push_data.episode == 0) & (push_data.step == 0)]
    assert np.array_equal(obs[0], first[0])
    _, short = labelled_states(push_data, {0: True}, tail=10, head=10_000)  # head stops short of the tail
    assert short.sum() == 10 and len(short) == steps[0]


def test_a_robots_raw_topic_session_trains_a_classifier_from_a_persons_labels(tmp_path):
    """A bag of a robot's raw topics (a `hil --online --from-topics` session: no transitions),
    a person's labels in it without an episode number: each is of the episode whose first
    state came last before it, and `classifier train` joins the topics and trains on them."""
    from raw_topic_bags import RAW_TOPICS, record_raw_bag

    from offline_rl_core.runs.classifier_run import bag_transitions

    plain = tmp_path / "plain.db3"
    record_raw_bag(plain, episodes=3, expert_frac=0.34, seed=4, sim_like=False, topics=RAW_TOPICS)
    _, starts = bag_transitions(plain)
    assert len(starts) == 3 and starts == sorted(starts)
    # the same session with a key pressed near each episode's end (the last one's after the log)
    pressed = ((starts[1] - 1_000_000, False), (starts[2] - 1_000_000, True), (starts[2] + 10**12, False))
    labelled = tmp_path / "labelled.db3"
    record_raw_bag(labelled, episodes=3, expert_frac=0.34, seed=4, sim_like=False, topics=RAW_TOPICS, labels=pressed)
    data, starts_again = bag_transitions(labelled)
    assert starts_again == starts
    assert episode_labels(labelled, starts) == {0: False, 1: True, 2: False}
    out = offline_rl("classifier", "train", "--bag", str(labelled), "--labels", "topic", "--successes", "1",
                     "--failures", "2", "--steps", "50", "--out", str(tmp_path / "cls.pt"))
    assert out.returncode == 0, out.stderr
    trained = load_classifier(tmp_path / "cls.pt")
    assert trained.contents["trained_on"]["success_episodes"] == 1 and trained.contents["trained_on"]["episodes"] == 3
    early = ((starts[0] - 1, True),)  # before any episode's first state: which episode cannot be told
    record_raw_bag(tmp_path / "early.db3", episodes=3, expert_frac=0.34, seed=4, sim_like=False, topics=RAW_TOPICS,
                   labels=early)
    with pytest.raises(UserError, match=r"early.db3: /episode_label: a label at .* before any episode's first state"):
        episode_labels(tmp_path / "early.db3", bag_transitions(tmp_path / "early.db3")[1])
