"""Each learner's loss on tiny cases computed by hand, the sampler, the checkpoint format."""

import math

import numpy as np
import pytest
import torch

from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.common.errors import UserError
from offline_rl_core.learners import TrainConfig, train, train_seeds
from offline_rl_core.learners.awac import AWAC
from offline_rl_core.learners.bc import BC
from offline_rl_core.learners.data import (
    Batch,
    IndexSampler,
    MemberData,
    correction_pools,
    intervention_actor_mask,
    top_episode_rows,
)
from offline_rl_core.learners.iql import IQL
from offline_rl_core.learners.naive import NaiveMaxQ
from offline_rl_core.serving.checkpoint import load_checkpoint, save_checkpoint
from offline_rl_core.serving.policy import load_policy
from offline_rl_core.data.transitions import SOURCE_HUMAN, SOURCE_POLICY

OBS, ACT, H = 3, 2, 4


def tiny_batch():
    obs = torch.tensor([[[0.5, -0.2, 0.1], [0.0, 0.3, -0.4]]])  # (M=1, B=2, 3)
    action = torch.tensor([[[0.6, -0.8], [-0.1, 0.2]]])
    reward = torch.tensor([[[-0.5], [1.0]]])
    next_obs = obs.flip(1)
    not_done = torch.tensor([[[1.0], [0.0]]])
    return Batch(obs, action, reward, next_obs, not_done, torch.ones(1, 2, 1), torch.zeros(1, 2, 1))


def zero_net(net, out_bias=0.0):
    with torch.no_grad():
        for w, b in zip(net.weights, net.biases):
            w.zero_()
            b.zero_()
        net.biases[-1].fill_(out_bias)


def action_reading_critic(net, coef):
    """Make every critic Q(s, a) = coef * (a_0 + 1): hidden unit 0 carries a_0 + 1."""
    zero_net(net)
    with torch.no_grad():
        net.weights[0][:, OBS + 0, 0] = 1.0  # input a_0 -> hidden 0
        net.biases[0][:, 0, 0] = 1.0  # +1 keeps it positive through the ReLU
        net.weights[1][:, 0, 0] = 1.0
        net.weights[2][:, 0, 0] = coef


def cfg(algo, **kw):
    # fp32: these check the maths to 1e-6; bf16 would round the hidden layer
    return TrainConfig(algo=algo, hidden=H, deterministic=True, **kw)


def test_bc_loss_is_mean_squared_error_to_logged_action():
    learner = BC(cfg("bc"), 1, [torch.Generator().manual_seed(0)], OBS, ACT)
    zero_net(learner.policy, out_bias=0.0)  # pi(s) = tanh(0) = 0
    batch = tiny_batch()
    loss = learner.update(batch)["policy_loss"]
    expected = np.mean(np.square([0.6, -0.8, -0.1, 0.2]))
    assert float(loss[0]) == pytest.approx(expected, rel=1e-6)


def test_awac_actor_loss_weights_each_sample_by_exp_advantage_over_beta():
    c = cfg("awac", beta=0.3, weight_clip=20.0)
    learner = AWAC(c, 1, [torch.Generator().manual_seed(0)], OBS, ACT)
    zero_net(learner.policy, out_bias=0.25)  # pi(s) = tanh(0.25) everywhere
    action_reading_critic(learner.critic.online, coef=0.5)
    batch = tiny_batch()
    loss = float(learner.actor_loss(batch)[0].detach())
    pi = math.tanh(0.25)
    expected = []
    for a in ([0.6, -0.8], [-0.1, 0.2]):
        adv = 0.5 * (a[0] + 1) - 0.5 * (pi + 1)  # Q(s, a) - Q(s, pi(s))
        w = min(math.exp(adv / 0.3), 20.0)
        expected.append(w * np.mean([(pi - a[0]) ** 2, (pi - a[1]) ** 2]))
    assert loss == pytest.approx(np.mean(expected), rel=1e-5)


def test_awac_weight_is_clipped():
    c = cfg("awac", beta=0.01, weight_clip=20.0)
    learner = AWAC(c, 1, [torch.Generator().manual_seed(0)], OBS, ACT)
    zero_net(learner.policy, out_bias=-2.0)  # pi(s) far below the logged a_0
    action_reading_critic(learner.critic.online, coef=1.0)
    batch = tiny_batch()
    pi = math.tanh(-2.0)
    expected = np.mean([20.0 * np.mean([(pi - a[0]) ** 2, (pi - a[1]) ** 2]) for a in ([0.6, -0.8], [-0.1, 0.2])])
    assert float(learner.actor_loss(batch)[0].detach()) == pytest.approx(expected, rel=1e-5)


def test_critic_target_bootstraps_min_target_q_except_at_termination():
    c = cfg("awac", gamma=0.9)
    learner = AWAC(c, 1, [torch.Generator().manual_seed(0)], OBS, ACT)
    zero_net(learner.critic.online, out_bias=0.0)  # online Q = 0
    zero_net(learner.critic.target, out_bias=2.0)  # both target Qs = 2
    with torch.no_grad():
        learner.critic.target.biases[-1][1] = 3.0  # second critic higher: min picks 2
    batch = tiny_batch()
    loss = float(learner.critic_update(batch)[0])
    targets = [-0.5 + 0.9 * 1.0 * 2.0, 1.0 + 0.9 * 0.0 * 2.0]  # terminated row: no bootstrap
    expected = 2 * np.mean(np.square(targets))  # q1 loss + q2 loss, both predict 0
    assert loss == pytest.approx(expected, rel=1e-6)


def test_naive_actor_maximises_min_q_of_its_own_action():
    learner = NaiveMaxQ(cfg("naive"), 1, [torch.Generator().manual_seed(0)], OBS, ACT)
    zero_net(learner.policy, out_bias=0.5)
    action_reading_critic(learner.critic.online, coef=2.0)
    loss = float(learner.actor_loss(tiny_batch())[0].detach())
    assert loss == pytest.approx(-2.0 * (math.tanh(0.5) + 1), rel=1e-6)


def test_iql_value_loss_is_the_expectile_loss():
    learner = IQL(cfg("iql", expectile=0.7), 1, [torch.Generator().manual_seed(0)], OBS, ACT)
    zero_net(learner.critic.target, out_bias=1.0)  # Q'(s, a) = 1
    zero_net(learner.value, out_bias=0.0)  # V(s) = 0 -> diff = +1 -> weight 0.7
    losses = learner.update(tiny_batch())
    assert float(losses["value_loss"][0]) == pytest.approx(0.7 * 1.0, rel=1e-6)
    learner2 = IQL(cfg("iql", expectile=0.7), 1, [torch.Generator().manual_seed(0)], OBS, ACT)
    zero_net(learner2.critic.target, out_bias=-1.0)  # diff = -1 -> weight 0.3
    zero_net(learner2.value, out_bias=0.0)
    assert float(learner2.update(tiny_batch())["value_loss"][0]) == pytest.approx(0.3, rel=1e-6)


def test_filtered_bc_keeps_the_top_episodes_by_return():
    data = collect_transitions(20, 0.3, 0)  # 6 expert episodes, return ~-2.3; random ~-16
    rows = top_episode_rows(data, 0.1)
    assert set(np.unique(data.episode[rows])) <= set(range(6))  # the best 10 % are expert episodes
    assert len(np.unique(data.episode[rows])) == 2


def synthetic_with_corrections():
    base = collect_transitions(4, 0.5, 0)
    src = base.source.copy()
    src[base.episode == 2] = SOURCE_POLICY
    src[(base.episode == 2) & (base.step >= 50) & (base.step < 60)] = SOURCE_HUMAN
    src[base.episode == 3] = SOURCE_POLICY
    base.source = src
    return base


def test_correction_ratio_sets_the_share_of_each_batch():
    data = synthetic_with_corrections()
    prior, corr = correction_pools(data)
    assert set(np.unique(data.source[corr])) == {SOURCE_POLICY, SOURCE_HUMAN}
    sampler = IndexSampler([len(data)], 64, [torch.Generator().manual_seed(0)],
                           [(torch.from_numpy(prior), torch.from_numpy(corr))], ratio=0.25)
    for _ in range(5):
        idx = sampler.next()[0].numpy()
        from_corr = np.isin(idx, corr).sum()
        assert from_corr == 16


def test_policy_actions_just_before_a_takeover_are_not_imitated():
    data = synthetic_with_corrections()
    mask = intervention_actor_mask(data, pre_steps=5)
    ep2 = data.episode == 2
    masked_steps = sorted(data.step[ep2 & (mask == 0)])
    assert masked_steps == [45, 46, 47, 48, 49]
    assert mask[data.episode != 2].min() == 1.0
    md = MemberData([data])
    assert float(md.actor_mask.sum()) == len(data) - 5


@pytest.mark.parametrize("algo", ["awac", "sac"])  # SAC: its policy noise too
def test_training_several_seeds_together_equals_training_each_alone(algo):
    d0, d1 = collect_transitions(4, 0.5, 0), collect_transitions(4, 0.5, 1)
    c = TrainConfig(algo=algo, steps=20, batch_size=16, hidden=16, log_every=10)
    both = train_seeds([d0, d1], c, [0, 1])
    alone = [train(d0, c, 0), train(d1, c, 1)]
    for together, single in zip(both, alone):
        for k, v in single.checkpoint["policy_state"].items():
            assert torch.equal(together.checkpoint["policy_state"][k], v)
        assert together.mean_abs_q == single.mean_abs_q


def test_same_seed_same_bytes_and_checkpoint_round_trip(tmp_path):
    data = collect_transitions(4, 0.5, 0)
    c = TrainConfig(algo="iql", steps=15, batch_size=16, hidden=16, log_every=5)
    a, b = train(data, c, 3), train(data, c, 3)
    assert a.history == b.history
    path = save_checkpoint(tmp_path / "p.pt", a.checkpoint)
    assert [p.name for p in tmp_path.iterdir()] == ["p.pt"]  # no temp file left behind
    ckpt = torch.load(path, weights_only=True)
    assert ckpt["algorithm"] == "iql" and ckpt["dataset_hash"] == data.content_hash()
    policy = load_policy(path)
    obs = data.obs[:7]
    np.testing.assert_allclose(policy.act(obs), a.policy.act(obs), rtol=0, atol=0)
    with torch.no_grad():
        torch_actions = policy.torch_module()(torch.from_numpy(obs)).numpy()
    np.testing.assert_allclose(policy.act(obs), torch_actions, atol=1e-6)
    assert np.all(np.abs(policy.act(obs)) <= 1.0)


def test_warm_start_from_a_checkpoint_continues_from_its_weights():
    data = collect_transitions(4, 0.5, 0)
    c = TrainConfig(algo="awac", steps=1, batch_size=16, hidden=16, lr=1e-12, log_every=1)
    first = train(data, c, 0)
    resumed = train(data, c, 5, init=first.checkpoint)
    for k, v in first.checkpoint["policy_state"].items():
        torch.testing.assert_close(resumed.checkpoint["policy_state"][k], v, atol=1e-6, rtol=0)
    assert torch.allclose(resumed.checkpoint["learner_state"]["critic1"]["0.weight"],
                          first.checkpoint["learner_state"]["critic1"]["0.weight"], atol=1e-6)


def test_bad_checkpoints_get_one_clear_line(tmp_path):
    missing = tmp_path / "nope.pt"
    with pytest.raises(UserError, match="no such checkpoint"):
        load_checkpoint(missing)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint at all")
    with pytest.raises(UserError, match="not a readable pusher-rl checkpoint"):
        load_checkpoint(garbage)
    small = train(collect_transitions(2, 0.5, 0), TrainConfig(algo="bc", steps=2, batch_size=2, hidden=8), 0)
    ckpt = dict(small.checkpoint, obs_dim=5)
    ckpt["policy_state"] = dict(ckpt["policy_state"], **{"0.weight": torch.zeros(8, 5)})
    small.checkpoint = ckpt
    path = save_checkpoint(tmp_path / "five.pt", small.checkpoint)
    with pytest.raises(UserError, match="obs_dim=5"):
        load_policy(path)
