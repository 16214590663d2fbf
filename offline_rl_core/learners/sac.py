"""SAC with a behaviour-cloning term on a person's corrections: the online (HIL-SERL) learner.

Policy: a tanh-squashed Gaussian. Its mean is the same network the offline learners
train (so an AWAC or BC checkpoint initialises it, and its deterministic action,
tanh(mean), is what a checkpoint serves); its log-std is one learnt vector.
Critic: r + gamma (1 - terminated) (min Q'(s', a') - alpha log pi(a' | s')), a' ~ pi(s'),
        MSE on both Qs, Polyak targets (the AWAC prior's critic initialises it).
Actor:  alpha log pi(a | s) - min Q(s, a), a ~ pi(s) reparameterised,
        plus ``bc_weight`` x the mean squared error of tanh(mean) to the person's action over
        the batch's rows a person chose (source "human") or labelled (``MemberData.append``'s
        labels: the corrector's action on a state the policy acted on).
alpha: fixed at ``alpha`` (with ``target_entropy`` set, tuned toward it instead).

Noise comes from each member's own generator, so a seed gives the same run, alone or
beside others.
"""

from __future__ import annotations

import math

import torch

from .base import CriticLearner, make_adam, per_member_mean
from .config import LOG_STD_MAX, LOG_STD_MIN


class SAC(CriticLearner):
    name = "sac"
    policy_tanh = False  # the network outputs the Gaussian's mean before the squashing

    def __init__(self, cfg, members, generators, obs_dim, act_dim):
        super().__init__(cfg, members, generators, obs_dim, act_dim)
        self.log_std = torch.nn.Parameter(torch.full((members, 1, act_dim), float(cfg.init_log_std), device=cfg.device))
        self.policy_opt = make_adam([*self.policy.parameters(), self.log_std], cfg.lr, cfg.device)
        self.log_alpha = torch.nn.Parameter(torch.full((members, 1, 1), math.log(cfg.alpha), device=cfg.device))
        self.alpha_opt = make_adam([self.log_alpha], cfg.lr, cfg.device) if cfg.target_entropy is not None else None
        # one noise stream per member, seeded from its own generator: a run's noise does not
        # depend on which runs train beside it (``loop.train_seeds``)
        self.noise_gens = [torch.Generator().manual_seed(int(torch.randint(0, 2**62, (1,), generator=g)))
                           for g in generators]

    def sample(self, mean):
        """(action, log pi(action)) with a ~ tanh(N(mean, std)), reparameterised:
        (M, B, A), (M, B, 1)."""
        log_std = self.log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)
        eps = torch.stack([torch.randn(mean.shape[1:], generator=g) for g in self.noise_gens]).to(mean.device)
        u = mean + log_std.exp() * eps
        action = torch.tanh(u)
        # log N(u; mean, std) minus log |d tanh(u) / du| = 2 (log 2 - u - softplus(-2u))
        log_prob = (-0.5 * eps.pow(2) - log_std - 0.5 * math.log(2 * math.pi)
                    - 2.0 * (math.log(2.0) - u - torch.nn.functional.softplus(-2.0 * u)))
        return action, log_prob.sum(-1, keepdim=True)

    def critic_update(self, batch, alpha) -> torch.Tensor:
        with torch.no_grad():
            next_action, next_log_prob = self.sample(self.policy(batch.next_obs))
            next_q = self.critic.q_min(batch.next_obs, next_action, target=True) - alpha * next_log_prob
            target_q = batch.reward + self.cfg.gamma * batch.not_done * next_q
        return self.critic.fit(batch.obs, batch.action, target_q)

    def actor_loss(self, batch, alpha):
        mean = self.policy(batch.obs)
        action, log_prob = self.sample(mean)
        self.critic.online.requires_grad_(False)  # the actor's loss moves the actor only
        q = self.critic.q_min(batch.obs, action)
        self.critic.online.requires_grad_(True)
        # BC on the person's actions: the mean over the batch's human rows (a handful of a
        # batch; a mean over the whole batch would dilute it by their share); a labelled row's
        # target is its label, not the policy's action that the critic learns from
        err = (torch.tanh(mean) - batch.label).pow(2).mean(-1, keepdim=True) * batch.human
        bc = err.flatten(1).sum(1) / batch.human.flatten(1).sum(1).clamp(min=1.0)
        return per_member_mean(alpha * log_prob - q) + self.cfg.bc_weight * bc, log_prob, q

    def critic_alone_update(self, batch):
        """The critic's step of ``update`` alone (the actor, its std and alpha stay): the
        current actor's values, fitted before it is moved (``OnlineSettings.critic_warmup``)."""
        critic_loss = self.critic_update(batch, self.log_alpha.detach().exp())
        self.critic.polyak()
        return {"critic_loss": critic_loss / 2}

    def update(self, batch):
        alpha = self.log_alpha.detach().exp()
        critic_loss = self.critic_update(batch, alpha)
        policy_loss, log_prob, q = self.actor_loss(batch, alpha)
        self.step_policy(policy_loss)
        if self.alpha_opt is not None:
            alpha_loss = per_member_mean(-self.log_alpha * (log_prob.detach() + self.cfg.target_entropy))
            self.alpha_opt.zero_grad(set_to_none=True)
            alpha_loss.sum().backward()
            self.alpha_opt.step()
        self.critic.polyak()
        return {"critic_loss": critic_loss / 2, "policy_loss": policy_loss.detach(), "alpha": alpha.flatten(),
                "log_std": self.log_std.detach().mean((1, 2)), "q_policy": q.detach().mean((1, 2))}

    def learner_state(self, m):
        return {**super().learner_state(m), "log_std": self.log_std[m, 0].detach().clone().cpu(),
                "log_alpha": self.log_alpha[m, 0, 0].detach().clone().cpu()}

    def load_learner_state(self, m, state):
        super().load_learner_state(m, state)
        with torch.no_grad():
            if "log_std" in state:
                self.log_std[m, 0].copy_(state["log_std"])
            if "log_alpha" in state and self.alpha_opt is not None:
                self.log_alpha[m, 0, 0].copy_(state["log_alpha"])
