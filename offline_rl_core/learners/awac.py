"""AWAC, the chapter's variant: a twin-Q critic plus advantage-weighted regression.

Critic: r + gamma (1 - terminated) min(Q1', Q2')(s', pi(s')), MSE on both.
Actor:  BC's regression, each sample weighted by exp((Q(s, a) - Q(s, pi(s))) / beta),
        clipped at ``weight_clip``, no gradient through the weight.
"""

from __future__ import annotations

import torch

from .base import CriticLearner, per_member_mean, regression_error


class AWAC(CriticLearner):
    name = "awac"

    def critic_update(self, batch) -> torch.Tensor:
        with torch.no_grad():
            next_q = self.critic.q_min(batch.next_obs, self.policy(batch.next_obs), target=True)
            target_q = batch.reward + self.cfg.gamma * batch.not_done * next_q
        return self.critic.fit(batch.obs, batch.action, target_q)

    def actor_loss(self, batch) -> torch.Tensor:
        pred = self.policy(batch.obs)
        with torch.no_grad():
            # Q of the logged action and of the policy's own, in one critic call
            both = self.critic.q_min(torch.cat([batch.obs, batch.obs], 1), torch.cat([batch.action, pred], 1))
            q_data, value = both.chunk(2, dim=1)
            weight = torch.exp((q_data - value) / self.cfg.beta).clamp(max=self.cfg.weight_clip)
        return per_member_mean(weight * regression_error(pred, batch.action) * batch.actor_mask)

    def update(self, batch):
        critic_loss = self.critic_update(batch)
        policy_loss = self.actor_loss(batch)
        self.step_policy(policy_loss)
        self.critic.polyak()
        return {"critic_loss": critic_loss / 2, "policy_loss": policy_loss.detach()}
