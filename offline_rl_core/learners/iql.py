"""IQL (Kostrikov et al. 2021): the critic never queries an action outside the data.

Value:  expectile regression of V(s) toward min Q'(s, a) over logged actions (tau 0.7).
Critic: r + gamma (1 - terminated) V(s'), MSE on both Qs, Polyak targets.
Actor:  advantage-weighted regression, weight exp(temperature * (min Q'(s, a) - V(s)))
        clipped at ``max_weight``. The policy here is deterministic (tanh MLP), so the
        log-likelihood of the paper becomes the same per-sample squared error as BC.
"""

from __future__ import annotations

import torch

from .base import CriticLearner, make_adam, make_network, per_member_mean, regression_error


class IQL(CriticLearner):
    name = "iql"

    def __init__(self, cfg, members, generators, obs_dim, act_dim):
        super().__init__(cfg, members, generators, obs_dim, act_dim)
        self.value = make_network(cfg, members, obs_dim, 1, generators)
        self.value_opt = make_adam(self.value.parameters(), cfg.lr, cfg.device)

    def update(self, batch):
        cfg = self.cfg
        with torch.no_grad():
            q_data = self.critic.q_min(batch.obs, batch.action, target=True)
        # value: asymmetric (expectile) regression toward the data's Q
        diff = q_data - self.value(batch.obs)
        weight = torch.abs(cfg.expectile - (diff < 0).float())
        value_loss = per_member_mean(weight * diff.pow(2))
        self.value_opt.zero_grad(set_to_none=True)
        value_loss.sum().backward()
        self.value_opt.step()
        # actor: advantage-weighted regression with the new V
        with torch.no_grad():
            v = self.value(batch.obs)
            adv_weight = torch.exp(cfg.temperature * (q_data - v)).clamp(max=cfg.max_weight)
            next_v = self.value(batch.next_obs)
            target_q = batch.reward + cfg.gamma * batch.not_done * next_v
        policy_loss = per_member_mean(adv_weight * regression_error(self.policy(batch.obs), batch.action) * batch.actor_mask)
        self.step_policy(policy_loss)
        # critic: TD toward r + gamma V(s')
        critic_loss = self.critic.fit(batch.obs, batch.action, target_q)
        self.critic.polyak()
        return {"critic_loss": critic_loss / 2, "value_loss": value_loss.detach(), "policy_loss": policy_loss.detach()}

    def learner_state(self, m):
        return {**super().learner_state(m), "value": self.value.member_state(m)}

    def load_learner_state(self, m, state):
        super().load_learner_state(m, state)
        if "value" in state:
            self.value.load_member_state(m, state["value"])
