"""``--algo auto`` picks the learner from what the bag holds; ``--budget-s`` becomes a step
count before training, reproducibly; the cosine learning rate replays like any step."""

import json

import numpy as np
import pytest
import torch

from offline_rl_core.commands import cli
from offline_rl_core.data.bag import write_transitions
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.learners import TrainConfig, train_seeds
from offline_rl_core.learners.data import goal_episode_rows, top_episode_rows
from offline_rl_core.learners.normalize import fold, unfold
from offline_rl_core.learners.schedule import lr_factor
from offline_rl_core.task.spec import load_task
from offline_rl_core.runs.prior import choose_recipe, plan_training, profile_bag, step_rate, steps_for_budget

TINY = ["--hidden", "32", "--batch-size", "32", "--eval-episodes", "2", "--log-every", "50"]


@pytest.fixture
def own_cache(tmp_path, monkeypatch):
    """A fresh measurement cache: the step rate is measured here, then reused."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache" / "pusher-rl"


def _bag(tmp_path, name, episodes, expert_frac):
    path = tmp_path / f"{name}.db3"
    write_transitions(path, collect_transitions(episodes, expert_frac, 0))
    return path


def _train(bag, out, *extra):
    return cli.main(["train", "--bag", str(bag), "--algo", "auto", "--out", str(out), *TINY, *extra])


def test_auto_clones_an_expert_only_bag_and_filters_a_mixed_one(tmp_path):
    expert = _bag(tmp_path, "expert", 12, 1.0)
    mixed = _bag(tmp_path, "mixed", 40, 0.3)
    assert _train(expert, tmp_path / "e", "--steps", "100") == 0
    assert _train(mixed, tmp_path / "m", "--steps", "100") == 0
    e = json.loads((tmp_path / "e" / "metrics.json").read_text())
    m = json.loads((tmp_path / "m" / "metrics.json").read_text())
    assert e["algorithm"] == "bc" and e["plan"]["profile"]["expert_like"] == 12
    assert m["algorithm"] == "filtered_bc" and m["plan"]["profile"]["expert_like"] == 12
    assert e["config"]["normalize_obs"] and m["config"]["normalize_obs"] and m["config"]["filter_by"] == "goal"
    assert e["steps"] == m["steps"] == 100  # --steps given: no budget


def test_the_filter_keeps_exactly_the_episodes_that_end_at_the_goal():
    data = collect_transitions(40, 0.3, 0)
    profile = profile_bag(data)
    assert profile.expert_like == 12 and profile.episodes == 40
    recipe = choose_recipe(profile)
    assert recipe.algo == "filtered_bc" and recipe.overrides["filter_by"] == "goal"
    rows = goal_episode_rows(data)
    assert set(np.unique(data.source[rows])) == {0}  # the expert's 12 episodes
    assert len(np.unique(data.episode[rows])) == 12
    # ranking by return instead would let in random episodes that started near the target
    by_return = top_episode_rows(data, 12 / 40)
    assert set(np.unique(data.source[by_return])) == {0, 1}


def test_too_few_demonstrations_fall_back_to_awac():
    random_only = profile_bag(collect_transitions(40, 0.0, 0))
    assert random_only.expert_like == 0
    assert choose_recipe(random_only).algo == "awac"
    few = profile_bag(collect_transitions(20, 0.15, 0))  # 3 demonstrations
    assert few.expert_like == 3 and choose_recipe(few).algo == "awac"
    enough = profile_bag(collect_transitions(20, 0.25, 0))  # 5
    assert choose_recipe(enough).algo == "filtered_bc"


def test_a_budget_becomes_the_same_steps_and_bytes_every_time(tmp_path, own_cache):
    bag = _bag(tmp_path, "mixed", 40, 0.3)
    assert _train(bag, tmp_path / "a", "--budget-s", "0.4") == 0
    assert (own_cache / "step_rates.json").exists()
    assert _train(bag, tmp_path / "b", "--budget-s", "0.4") == 0
    a = (tmp_path / "a" / "metrics.json").read_bytes()
    assert a == (tmp_path / "b" / "metrics.json").read_bytes()
    plan = json.loads(a)["plan"]
    assert plan["steps"] == json.loads(a)["steps"] == steps_for_budget(0.4, plan["steps_per_s"])
    assert plan["budget_s"] == 0.4 and plan["budget_from"] == "--budget-s"
    # the recorded steps reproduce the run without the budget
    assert _train(bag, tmp_path / "c", "--steps", str(plan["steps"])) == 0
    pa = torch.load(tmp_path / "a" / "policy.pt", weights_only=True)["policy_state"]
    pc = torch.load(tmp_path / "c" / "policy.pt", weights_only=True)["policy_state"]
    assert all(torch.equal(pa[k], pc[k]) for k in pa)


def test_steps_for_budget_spends_a_fixed_share_in_whole_hundreds():
    assert steps_for_budget(10.0, 1000.0) == 8500
    assert steps_for_budget(10.0, 1001.0) == 8500
    assert steps_for_budget(0.01, 1000.0) == 100  # never zero


def test_steps_and_budget_together_is_one_clear_error(tmp_path, capsys):
    bag = _bag(tmp_path, "mixed", 4, 0.5)
    assert _train(bag, tmp_path / "x", "--steps", "100", "--budget-s", "5") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == "offline-rl: error: give --steps or --budget-s, not both"
    assert not (tmp_path / "x").exists()


def test_cosine_rate_replays_byte_identically_and_changes_the_run(monkeypatch):
    assert lr_factor("cosine", 1, 100) == 1.0 and lr_factor("cosine", 100, 100) < 1e-3
    data = collect_transitions(10, 0.5, 0)
    cfg = dict(algo="bc", steps=30, log_every=10, batch_size=32, hidden=32)

    def run(mode, schedule):
        monkeypatch.setenv("PUSHER_RL_STEP", mode)
        return train_seeds(data, TrainConfig(**cfg, lr_schedule=schedule), [0])[0].checkpoint["policy_state"]

    eager, replayed, constant = run("autograd", "cosine"), run("auto", "cosine"), run("auto", "constant")
    assert all(torch.equal(eager[k], replayed[k]) for k in eager)
    assert not all(torch.equal(eager[k], constant[k]) for k in eager)


def test_normalised_training_saves_networks_of_raw_observations():
    """Folding the z-scoring into the first layer gives the same function of raw
    observations (policy, and critics whose inputs begin with the observation), and
    unfolding (a warm start) inverts it."""
    gen = torch.Generator().manual_seed(0)
    mean, std = np.array([0.5, -1.0, 0.02], np.float32), np.array([2.0, 0.5, 0.05], np.float32)
    net = {"0.weight": torch.randn(6, 5, generator=gen), "0.bias": torch.randn(6, generator=gen)}
    state = {"critic1": net, "other": 3}
    x = torch.randn(4, 3, generator=gen, dtype=torch.float32)
    a = torch.randn(4, 2, generator=gen)
    z = (x - torch.from_numpy(mean)) / torch.from_numpy(std)
    folded = fold(state, mean, std)
    want = torch.cat([z, a], 1) @ net["0.weight"].T + net["0.bias"]
    got = torch.cat([x, a], 1) @ folded["critic1"]["0.weight"].T + folded["critic1"]["0.bias"]
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    assert folded["other"] == 3
    back = unfold(folded, mean, std)["critic1"]
    torch.testing.assert_close(back["0.weight"], net["0.weight"])
    torch.testing.assert_close(back["0.bias"], net["0.bias"], rtol=1e-5, atol=1e-5)


def test_a_normalised_run_acts_on_raw_observations_and_warm_starts(tmp_path):
    data = collect_transitions(10, 0.5, 0)
    cfg = TrainConfig(algo="filtered_bc", filter_by="goal", normalize_obs=True, steps=200, log_every=100,
                      batch_size=32, hidden=32)
    first = train_seeds(data, cfg, [0])[0]
    assert first.checkpoint["obs_mean"] is None  # folded into the weights
    obs = data.obs[:50]
    imitation = np.abs(first.policy.act(obs) - data.action[:50]).mean()
    untrained = train_seeds(data, TrainConfig(**{**cfg.to_dict(), "steps": 1}), [0])[0]
    assert imitation < np.abs(untrained.policy.act(obs) - data.action[:50]).mean()
    # a warm start from it, at a learning rate too small to move it, gives it back
    again = train_seeds(data, TrainConfig(**{**cfg.to_dict(), "steps": 1, "lr": 1e-12}), [1],
                        init=first.checkpoint)[0]
    np.testing.assert_allclose(again.policy.act(obs), first.policy.act(obs), atol=1e-4)


def test_auto_stops_when_the_cloned_rows_need_no_more_steps(own_cache):
    data = collect_transitions(10, 0.5, 0)  # 5 demonstrations, 500 rows
    cfg, plan = plan_training(data, TrainConfig(batch_size=32, hidden=32), True, 1e6, None)
    assert plan["max_steps"] == 15700 == cfg.steps < plan["budget_steps"]  # 1000 passes over 500 rows
    bc, _ = plan_training(data, TrainConfig(algo="bc", batch_size=32, hidden=32), False, 1.0, None)
    assert bc.steps == steps_for_budget(1.0, step_rate(bc, data))  # a learner given by name: the budget alone


def test_the_step_rate_of_filtered_bc_by_goal_is_measured_on_the_datas_own_task(own_cache):
    """On a machine that has not measured it yet, the step rate of an auto plan that clones the
    episodes ending at the goal is timed on the data's task: pusher_push's episodes end at the
    goal by its columns, not by pusher_reach's (the first `--algo auto` on a new machine failed so)."""
    data = collect_transitions(4, 1.0, 4, task="pusher_push")  # resets 4..7: the expert pushes each home
    task = load_task("pusher_push")
    cfg = TrainConfig(algo="filtered_bc", filter_by="goal", batch_size=32, hidden=32)
    with pytest.raises(ValueError, match="no episode of the data ends at the goal"):
        goal_episode_rows(data)  # pusher_reach's columns
    assert len(goal_episode_rows(data, task)) == len(data)
    assert step_rate(cfg, data, lambda s: None, task) > 0
    assert (own_cache / "step_rates.json").is_file()


def test_the_online_stage_reuses_an_auto_prior_only_of_the_same_data_and_seed(tmp_path, own_cache, monkeypatch):
    from offline_rl_core.runs import prior
    from offline_rl_core.pipelines.hil import reusable_auto_prior

    monkeypatch.setattr(prior, "chapter_awac_seconds", lambda data, log=None: 0.5)  # the default budget, short
    mixed, other = _bag(tmp_path, "mixed", 40, 0.3), tmp_path / "other.db3"
    write_transitions(other, collect_transitions(40, 0.3, 1))
    assert _train(mixed, tmp_path / "auto", "--seed", "2") == 0
    assert _train(mixed, tmp_path / "fixed", "--seed", "2", "--steps", "100") == 0
    ckpt = tmp_path / "auto" / "policy.pt"
    assert reusable_auto_prior(ckpt, [str(mixed)], 2)
    assert not reusable_auto_prior(ckpt, [str(mixed)], 3)
    assert not reusable_auto_prior(ckpt, [str(other)], 2)
    assert not reusable_auto_prior(tmp_path / "fixed" / "policy.pt", [str(mixed)], 2)  # not the default budget


def test_a_step_rate_measured_on_a_busy_machine_says_so_and_keeps_the_load(own_cache, monkeypatch):
    """Budgets in seconds (equal wall time) follow the cached rate for good: one measured while
    other work competes for the cores warns, and the cache keeps the load it was taken under."""
    import offline_rl_core.runs.prior as prior

    monkeypatch.setattr(prior.os, "getloadavg", lambda: (99.0, 99.0, 99.0))
    data = collect_transitions(2, 1.0, 0)
    said = []
    assert step_rate(TrainConfig(algo="bc", batch_size=32, hidden=32), data, said.append) > 0
    assert any(line.startswith("warning: the machine is busy (load 99.0 on") for line in said)
    entry, = json.loads((own_cache / "step_rates.json").read_text()).values()
    assert entry["load"] == 99.0 and entry["cores"] >= 1
