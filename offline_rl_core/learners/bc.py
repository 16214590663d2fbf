"""Behaviour cloning: regress the logged action, every sample weighted the same."""

from __future__ import annotations

from .base import Learner, per_member_mean, regression_error


class BC(Learner):
    name = "bc"

    def update(self, batch):
        err = regression_error(self.policy(batch.obs), batch.action)
        loss = per_member_mean(err * batch.actor_mask)  # the one line that differs: weight 1
        self.step_policy(loss)
        return {"policy_loss": loss.detach()}
