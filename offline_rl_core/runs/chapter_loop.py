"""The chapter's training loop, written plainly: the baseline the learners are timed against.

Two separate ``Critic`` modules, ``torch.randint`` from the global RNG for each batch,
``torch.optim.Adam`` with default options, a Python loop for the Polyak update, and a
per-step ``.item()`` to read the mean Q. Same maths as ``offline_rl_core.learners``
(AWAC's critic target, advantage weight and weighted regression; BC's MSE), so a test
can check that both land in the same place; only the speed differs.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..data.transitions import Transitions
from ..learners.config import TrainConfig


class Policy(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int, hidden: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(obs_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, act_dim))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.net(obs))


class Critic(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int, hidden: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(obs_dim + act_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, 1))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, action], dim=1))


@dataclass
class ChapterSettings:
    """The chapter's hyper-parameters: ``TrainConfig``'s defaults, where they are written once."""

    steps: int = TrainConfig.steps
    batch_size: int = TrainConfig.batch_size
    hidden: int = TrainConfig.hidden
    lr: float = TrainConfig.lr
    gamma: float = TrainConfig.gamma
    tau: float = TrainConfig.tau
    beta: float = TrainConfig.beta
    weight_clip: float = TrainConfig.weight_clip


def dataset_tensors(data: Transitions, device: str = "cpu") -> dict[str, torch.Tensor]:
    """The chapter's dataset dict: obs, action, reward (N, 1), next_obs, terminated (N, 1),
    on ``device`` (the networks follow the data there)."""
    tensors = {
        "obs": torch.tensor(data.obs, dtype=torch.float32),
        "action": torch.tensor(data.action, dtype=torch.float32),
        "reward": torch.tensor(data.reward, dtype=torch.float32).unsqueeze(1),
        "next_obs": torch.tensor(data.next_obs, dtype=torch.float32),
        "terminated": torch.tensor(data.terminated.astype(np.float32)).unsqueeze(1),
    }
    return {k: v.to(device) for k, v in tensors.items()}


def _sampler(data: dict[str, torch.Tensor], batch_size: int):
    n = len(data["obs"])
    device = data["obs"].device

    def sample_batch():
        idx = torch.randint(0, n, (batch_size,), device=device)  # the global torch RNG, as the chapter does
        return data["obs"][idx], data["action"][idx], data["reward"][idx], data["next_obs"][idx], data["terminated"][idx]

    return sample_batch


def train_bc(data: dict[str, torch.Tensor], s: ChapterSettings) -> Policy:
    obs_dim, act_dim = data["obs"].shape[1], data["action"].shape[1]
    sample_batch = _sampler(data, s.batch_size)
    policy = Policy(obs_dim, act_dim, s.hidden).to(data["obs"].device)
    opt = torch.optim.Adam(policy.parameters(), lr=s.lr)
    for _ in range(s.steps):
        obs, action, *_ = sample_batch()
        loss = F.mse_loss(policy(obs), action)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return policy


def train_awac(data: dict[str, torch.Tensor], s: ChapterSettings) -> tuple[Policy, float]:
    """AWAC as the chapter writes it; returns the policy and the final mean Q on the batch."""
    policy, _, _, mean_q = train_awac_with_critics(data, s)
    return policy, mean_q


def train_awac_with_critics(data: dict[str, torch.Tensor], s: ChapterSettings) -> tuple[Policy, Critic, Critic, float]:
    obs_dim, act_dim = data["obs"].shape[1], data["action"].shape[1]
    sample_batch = _sampler(data, s.batch_size)
    device = data["obs"].device
    policy = Policy(obs_dim, act_dim, s.hidden).to(device)
    q1, q2 = Critic(obs_dim, act_dim, s.hidden).to(device), Critic(obs_dim, act_dim, s.hidden).to(device)
    q1_targ = copy.deepcopy(q1).requires_grad_(False)
    q2_targ = copy.deepcopy(q2).requires_grad_(False)
    policy_opt = torch.optim.Adam(policy.parameters(), lr=s.lr)
    critic_opt = torch.optim.Adam(list(q1.parameters()) + list(q2.parameters()), lr=s.lr)
    mean_q = float("nan")
    for _ in range(s.steps):
        obs, action, reward, next_obs, terminated = sample_batch()
        with torch.no_grad():
            next_action = policy(next_obs)
            min_next_q = torch.min(q1_targ(next_obs, next_action), q2_targ(next_obs, next_action))
            target_q = reward + s.gamma * (1.0 - terminated) * min_next_q
        critic_loss = F.mse_loss(q1(obs, action), target_q) + F.mse_loss(q2(obs, action), target_q)
        critic_opt.zero_grad()
        critic_loss.backward()
        critic_opt.step()

        pred = policy(obs)
        with torch.no_grad():
            q_data = torch.min(q1(obs, action), q2(obs, action))
            value = torch.min(q1(obs, pred), q2(obs, pred))
            weight = torch.exp((q_data - value) / s.beta).clamp(max=s.weight_clip)
        policy_loss = (weight * (pred - action).pow(2).mean(1, keepdim=True)).mean()
        policy_opt.zero_grad()
        policy_loss.backward()
        policy_opt.step()

        with torch.no_grad():
            for online, targ in ((q1, q1_targ), (q2, q2_targ)):
                for p, tp in zip(online.parameters(), targ.parameters()):
                    tp.mul_(1.0 - s.tau).add_(s.tau * p)
        mean_q = 0.5 * (q1(obs, action) + q2(obs, action)).mean().item()  # a host sync every step
    return policy, q1, q2, mean_q


def policy_act_fn(policy: Policy):
    """The chapter's evaluation call: one torch forward per observation batch."""

    @torch.no_grad()
    def act(obs: np.ndarray) -> np.ndarray:
        return policy(torch.as_tensor(obs, dtype=torch.float32)).numpy()

    return act


def steps_per_second(algo: str, data: dict[str, torch.Tensor], s: ChapterSettings, seed: int = 0) -> float:
    torch.manual_seed(seed)
    t0 = time.perf_counter()
    (train_awac if algo == "awac" else train_bc)(data, s)
    if data["obs"].is_cuda:  # BC never syncs: wait for the queued kernels
        torch.cuda.synchronize(data["obs"].device)
    return s.steps / (time.perf_counter() - t0)


def run_chapter_experiment(episodes: int, expert_frac: float, seed: int, s: ChapterSettings,
                           n_seeds: int = 5, eval_episodes: int = 20) -> dict:
    """One full chapter run: collect, train BC, train AWAC, evaluate both one episode at
    a time. Returns the pooled success rates (for a sanity check; timing is the point)."""
    from ..data.collect import collect_transitions
    from ..evaluation.rollouts import rollout
    from ..common.seeds import eval_reset_seeds

    torch.manual_seed(seed)
    data = dataset_tensors(collect_transitions(episodes, expert_frac, seed))
    bc = train_bc(data, s)
    awac, mean_q = train_awac(data, s)
    seeds = eval_reset_seeds(seed, n_seeds, eval_episodes)
    bc_roll = rollout(policy_act_fn(bc), seeds, batched=False)
    awac_roll = rollout(policy_act_fn(awac), seeds, batched=False)
    return {"bc_success_rate": bc_roll.success_rate, "offline_success_rate": awac_roll.success_rate,
            "offline_mean_abs_q": abs(mean_q)}
