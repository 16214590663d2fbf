"""Datasets both ways: a bag as a Minari dataset that Minari's own reader opens, back to the
same rows; a foreign Minari dataset into a bag; d3rlpy trained from a bag (the README's recipe)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from offline_rl_core.commands.cli import main
from offline_rl_core.data.bag import read_transitions, write_transitions
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.data.transitions import SOURCE_BY_NAME

minari = pytest.importorskip("minari")


@pytest.fixture(autouse=True)
def minari_root(tmp_path, monkeypatch):
    root = tmp_path / "minari"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    return root


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    """Three episodes as the sim records them, a step lost in the middle of the second, and a
    last episode cut off (a recording stopped mid-episode: neither flag set)."""
    data = collect_transitions(4, 0.5, 0)
    keep = np.ones(len(data), dtype=bool)
    keep[150] = False  # episode 1 loses a step: its observations no longer chain there
    keep[350:] = False  # episode 3 stops after 50 steps
    path = tmp_path_factory.mktemp("bag") / "gaps.db3"
    write_transitions(path, data.select(keep))
    return path


def test_a_bag_exported_to_minari_opens_there_and_imports_back_to_the_same_rows(bag, tmp_path, capsys):
    assert main(["export", "--minari", "pusher/gaps-v0", str(bag)]) == 0
    dataset = minari.load_dataset("pusher/gaps-v0")
    rows = read_transitions(bag)
    assert dataset.total_steps == len(rows) == 349
    assert dataset.total_episodes == 5  # 4 episode ids, one of them split where its step was lost
    assert dataset.observation_space.shape == (8,) and np.isinf(dataset.observation_space.high).all()
    assert dataset.action_space.shape == (2,)
    assert (dataset.action_space.low == -1).all() and (dataset.action_space.high == 1).all()
    episodes = list(dataset.iterate_episodes())
    assert [len(ep) for ep in episodes] == [100, 50, 49, 100, 50]
    first, cut = episodes[0], episodes[-1]
    assert np.array_equal(first.observations[:-1], rows.obs[:100])
    assert np.array_equal(first.observations[1:], rows.next_obs[:100])
    assert np.array_equal(first.actions, rows.action[:100]) and np.array_equal(first.rewards, rows.reward[:100])
    assert first.truncations[-1] and not first.truncations[:-1].any() and not first.terminations.any()
    assert not cut.truncations.any() and not cut.terminations.any()  # as it was: cut off, not ended
    assert list(first.infos["source"][1:3]) == [SOURCE_BY_NAME["expert"]] * 2
    assert dataset.recover_environment().spec.id == "offline_rl_core/PusherReach-v0"

    out = tmp_path / "back.db3"
    assert main(["import", "--minari", "pusher/gaps-v0", str(out)]) == 0
    assert np.array_equal(read_transitions(out).to_rows(), rows.to_rows())


def test_export_refuses_what_it_cannot_write_in_one_line(bag, capsys):
    assert main(["export", "--minari", "pusher/gaps-v0", str(bag)]) == 0
    assert main(["export", "--minari", "pusher/gaps-v0", str(bag)]) == 2  # never overwritten
    assert "a Minari dataset of that ID exists" in capsys.readouterr().err
    assert main(["export", "--minari", "no version", str(bag)]) == 2
    assert "not a Minari dataset ID; expected [NAMESPACE/]NAME-vN" in capsys.readouterr().err
    assert main(["import", "--minari", "pusher/none-v0", "x.db3"]) == 2
    assert "pusher/none-v0: no such Minari dataset in" in capsys.readouterr().err


def _foreign(dataset_id: str, scale: float = 1.0):
    """A Minari dataset as another tool writes it: no pusher-rl infos."""
    from minari.data_collector import EpisodeBuffer

    from offline_rl_core.data.interop import spaces

    data = collect_transitions(2, 1.0, 3)
    buffers = [EpisodeBuffer(id=i, observations=np.concatenate([data.obs[rows], data.next_obs[rows][-1:]]),
                             actions=data.action[rows] * scale, rewards=data.reward[rows],
                             terminations=data.terminated[rows], truncations=data.truncated[rows])
               for i, rows in enumerate((slice(0, 100), slice(100, 200)))]
    obs_space, act_space = spaces(8, 2)
    minari.create_dataset_from_buffers(dataset_id, buffers, observation_space=obs_space, action_space=act_space)
    return data


def test_a_foreign_minari_dataset_imports_with_the_source_it_is_given(tmp_path, capsys):
    data = _foreign("other/expert-v0")
    out = tmp_path / "expert.db3"
    assert main(["import", "--minari", "other/expert-v0", str(out)]) == 2
    assert "does not record who acted; say it with --source" in capsys.readouterr().err
    assert not out.exists()
    assert main(["import", "--minari", "other/expert-v0", str(out), "--source", "expert"]) == 0
    back = read_transitions(out)
    assert np.array_equal(back.obs, data.obs) and np.array_equal(back.next_obs, data.next_obs)
    assert np.array_equal(back.action, data.action) and np.array_equal(back.truncated, data.truncated)
    assert (back.source == SOURCE_BY_NAME["expert"]).all()
    assert list(np.unique(back.episode)) == [0, 1] and list(back.step[:3]) == [0, 1, 2]

    _foreign("other/wide-v0", scale=2.0)
    assert main(["import", "--minari", "other/wide-v0", str(tmp_path / "w.db3"), "--source", "policy"]) == 2
    assert "actions lie outside [-1, 1]" in capsys.readouterr().err


def test_d3rlpy_trains_from_a_bag_as_the_readme_says(bag):
    """The README's recipe ("Where users already look"), on a small bag and few steps."""
    d3rlpy = pytest.importorskip("d3rlpy")
    from offline_rl_core.data.interop import d3rlpy_dataset
    from offline_rl_core.evaluation.rollouts import evaluate_policy

    torch.set_num_threads(1)
    transitions = read_transitions(bag)
    dataset = d3rlpy_dataset(transitions)
    assert [ep.size() for ep in dataset.episodes] == [100, 50, 49, 100, 50]
    # d3rlpy has no next observation for the last step of an episode that did not terminate
    assert dataset.transition_count == len(transitions) - 5
    awac = d3rlpy.algos.AWACConfig(batch_size=32).create(device="cpu:0")
    awac.fit(dataset, n_steps=20, n_steps_per_epoch=20, show_progress=False,
             logger_adapter=d3rlpy.logging.NoopAdapterFactory())
    actions = awac.predict(transitions.obs[:5])
    assert actions.shape == (5, 2) and np.all(np.abs(actions) <= 1.0)
    result = evaluate_policy(awac.predict, episodes=2, seed=500000)  # the held-out resets, as ours are scored
    assert result["episodes"] == 2 and 0.0 <= result["success_rate"] <= 1.0


def test_another_arms_bag_goes_to_minari_and_back_with_its_task(tmp_path, capsys):
    from offline_rl_core.data.task_record import recorded_task
    from offline_rl_core.task.spec import load_task

    task = load_task("pusher7_reach")
    bag = tmp_path / "arm7.db3"
    write_transitions(bag, collect_transitions(2, 0.5, 0, task=task), task=task)
    assert main(["export", "--minari", "pusher/arm7-v0", str(bag)]) == 0  # the task the bag records
    dataset = minari.load_dataset("pusher/arm7-v0")
    assert dataset.observation_space.shape == (task.obs_dim,) and dataset.action_space.shape == (task.act_dim,)
    assert dataset.spec.env_spec is None  # no Gymnasium env of that arm to name
    assert "pusher7_reach" in dataset.storage.metadata["description"]

    out = tmp_path / "back.db3"
    assert main(["import", "--minari", "pusher/arm7-v0", str(out)]) == 2  # read as pusher_reach: sizes differ
    err = capsys.readouterr().err
    assert "task pusher_reach has 8 and 2 (give the dataset's task with --task)" in err and not out.exists()
    assert main(["import", "--minari", "pusher/arm7-v0", str(out), "--task", "pusher7_reach"]) == 0
    assert np.array_equal(read_transitions(out).to_rows(), read_transitions(bag).to_rows())
    assert recorded_task(out).digest == task.digest  # train --bag OUT knows its task
