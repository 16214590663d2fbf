"""Naive offline RL (the Break-It): AWAC's critic, but the actor maximises Q directly,
with no anchor to the logged actions. On narrow data the critic overestimates
actions it never saw and the policy chases them."""

from __future__ import annotations

from .awac import AWAC
from .base import per_member_mean


class NaiveMaxQ(AWAC):
    name = "naive"

    def actor_loss(self, batch):
        pred = self.policy(batch.obs)
        # gradients also reach the critic here; its optimiser clears them before its next step
        return -per_member_mean(self.critic.q_min(batch.obs, pred))
