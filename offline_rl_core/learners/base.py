"""What every learner shares: the policy ensemble, its optimiser, the critic helpers.

A learner sees tensors shaped (members, batch, dim) and returns per-member losses
as tensors (no host sync in the step; the loop reads them every ``log_every`` steps).
"""

from __future__ import annotations

import torch

from .networks import EnsembleMLP
from .config import TrainConfig
from .data import Batch, MemberData
from . import acceleration


def make_adam(params, lr: float, device: str = "cpu") -> torch.optim.Adam:
    # fused: one kernel for the whole update instead of several per parameter.
    # capturable on CUDA:
    # its step counter stays on the GPU, so the step can be recorded in a CUDA graph.
    return torch.optim.Adam(params, lr=lr, fused=True, capturable=torch.device(device).type == "cuda")


def make_network(cfg: TrainConfig, members: int, in_dim: int, out_dim: int, generators=None,
                 tanh_output: bool = False) -> EnsembleMLP:
    """An ensemble MLP of the config's width, on the config's device (on the CPU, with the
    speed layer's forward where one is registered and covers it). Weights are drawn on the
    CPU from the members' generators first, so a seed gives the same initial network on
    every device."""
    net = EnsembleMLP(members, in_dim, cfg.hidden, out_dim, generators, tanh_output=tanh_output)
    layer = acceleration.registered()
    if cfg.device == "cpu" and layer is not None and (fast := layer.network_forward(net, cfg)) is not None:
        net.cpu_forward, net.kernels = fast
    return net.to(cfg.device)


def per_member_mean(x: torch.Tensor) -> torch.Tensor:
    """(M, B, ...) -> (M,) means. Summing these over members gives each member the
    gradient of its own mean loss: members never mix."""
    return x.flatten(1).mean(1)


class Learner:
    """Base: a tanh policy ensemble trained by ``policy_loss``; no critic."""

    name = "base"
    uses_critic = False
    policy_tanh = True  # the policy network ends in tanh (False: it outputs a pre-squash mean)

    def __init__(self, cfg: TrainConfig, members: int, generators: list[torch.Generator], obs_dim: int, act_dim: int):
        self.cfg = cfg
        self.members = members
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.policy = make_network(cfg, members, obs_dim, act_dim, generators, tanh_output=self.policy_tanh)
        self.policy_opt = make_adam(self.policy.parameters(), cfg.lr, cfg.device)

    def update(self, batch: Batch) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    def step_policy(self, loss_per_member: torch.Tensor) -> None:
        self.policy_opt.zero_grad(set_to_none=True)
        loss_per_member.sum().backward()
        self.policy_opt.step()

    def mean_abs_q(self, data: MemberData) -> list[float] | None:
        return None

    def learner_state(self, m: int) -> dict:
        return {}

    def load_learner_state(self, m: int, state: dict) -> None:
        pass


class CriticLearner(Learner):
    """A learner with a twin Q critic (AWAC, IQL, SAC, naive): the critic is built after the
    policy, reports the Break-It |Q|, and is saved and restored with the learner's state."""

    uses_critic = True

    def __init__(self, cfg: TrainConfig, members: int, generators: list[torch.Generator], obs_dim: int, act_dim: int):
        super().__init__(cfg, members, generators, obs_dim, act_dim)
        self.critic = TwinCritic(cfg, members, generators, obs_dim, act_dim)

    def mean_abs_q(self, data: MemberData) -> list[float]:
        return self.critic.mean_abs_q(data)

    def learner_state(self, m: int) -> dict:
        return self.critic.state(m)

    def load_learner_state(self, m: int, state: dict) -> None:
        if "critic1" in state:  # a BC checkpoint's learner state has no critic
            self.critic.load_state(m, state)


def regression_error(pred: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """Per-sample squared error, averaged over action dims: (M, B, 1)."""
    return (pred - action).pow(2).mean(-1, keepdim=True)


class TwinCritic:
    """Two Q(s, a) networks per member, stacked as one ensemble of 2M, with Polyak
    targets. Member m's critics are rows 2m and 2m+1."""

    def __init__(self, cfg: TrainConfig, members: int, generators, obs_dim: int, act_dim: int):
        self.members = members
        gens = [g for g in generators for _ in range(2)]
        self.online = make_network(cfg, 2 * members, obs_dim + act_dim, 1, gens)
        self.target = make_network(cfg, 2 * members, obs_dim + act_dim, 1)
        self.target.load_state_dict(self.online.state_dict())
        self.target.requires_grad_(False)
        self.opt = make_adam(self.online.parameters(), cfg.lr, cfg.device)
        self.tau = cfg.tau

    def _pairs(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        x = torch.cat([obs, action], dim=-1)  # (M, B, in)
        m, b, d = x.shape
        return x.unsqueeze(1).expand(m, 2, b, d).reshape(2 * m, b, d)

    def q_both(self, obs, action, target: bool = False) -> torch.Tensor:
        """(M, 2, B, 1): both critics' Q for each member."""
        net = self.target if target else self.online
        q = net(self._pairs(obs, action))
        return q.view(self.members, 2, *q.shape[1:])

    def q_min(self, obs, action, target: bool = False) -> torch.Tensor:
        return self.q_both(obs, action, target).min(dim=1).values

    def fit(self, obs, action, target_q: torch.Tensor) -> torch.Tensor:
        """One MSE step of both critics toward ``target_q`` (M, B, 1); per-member loss
        (q1 loss + q2 loss, the chapter's sum)."""
        q = self.q_both(obs, action)
        loss = (q - target_q.unsqueeze(1)).pow(2).flatten(2).mean(2).sum(1)
        self.opt.zero_grad(set_to_none=True)
        loss.sum().backward()
        self.opt.step()
        return loss.detach()

    @torch.no_grad()
    def polyak(self) -> None:
        online = list(self.online.parameters())
        target = list(self.target.parameters())
        torch._foreach_lerp_(target, online, self.tau)

    @torch.no_grad()
    def mean_abs_q(self, data: MemberData, chunk: int = 4096) -> list[float]:
        """|mean over the logged (s, a) of (Q1 + Q2) / 2|, per member (the chapter's
        Break-It figure), over the whole dataset.

        The critics run in chunks (their activations for a 2M-row bag would be GBs); the
        per-row Qs are kept (8 bytes a row, in one buffer allocated up front: small
        per-chunk tensors left between the chunks' freed activations fragment the heap
        on a large bag) and summed once, so the figure does not depend on
        the chunk size."""
        device = data.obs.device
        sizes = torch.tensor(data.sizes, device=device)
        n = max(data.sizes)
        q = torch.empty(self.members, n, dtype=torch.float64, device=device)
        for lo in range(0, n, chunk):
            obs = data.obs[:, lo: lo + chunk].expand(self.members, -1, -1)
            act = data.action[:, lo: lo + chunk].expand(self.members, -1, -1)
            q[:, lo: lo + chunk] = self.q_both(obs, act).mean(1)[..., 0]  # (M, b)
        valid = torch.arange(n, device=device).unsqueeze(0) < sizes.unsqueeze(1)
        totals = (q * valid).sum(1)
        return [abs(float(totals[m]) / data.sizes[m]) for m in range(self.members)]

    def state(self, m: int) -> dict:
        return {"critic1": self.online.member_state(2 * m), "critic2": self.online.member_state(2 * m + 1),
                "critic1_target": self.target.member_state(2 * m), "critic2_target": self.target.member_state(2 * m + 1)}

    def load_state(self, m: int, state: dict) -> None:
        self.online.load_member_state(2 * m, state["critic1"])
        self.online.load_member_state(2 * m + 1, state["critic2"])
        self.target.load_member_state(2 * m, state.get("critic1_target", state["critic1"]))
        self.target.load_member_state(2 * m + 1, state.get("critic2_target", state["critic2"]))
