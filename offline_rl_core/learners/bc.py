"""Behaviour cloning: regress the logged action, every sample weighted the same."""

from __future__ import annotations

from .base import Learner, per_member_mean, regression_error
from .written_out import written_out_step


class BC(Learner):
    name = "bc"

    def __init__(self, cfg, members, generators, obs_dim, act_dim):
        super().__init__(cfg, members, generators, obs_dim, act_dim)
        # the same update with the backward written out, on the CPU (see written_out)
        self._written_out = written_out_step(self, "bc") if type(self).update is BC.update else None

    def update(self, batch):
        if self._written_out is not None:
            return self._written_out(batch)
        err = regression_error(self.policy(batch.obs), batch.action)
        loss = per_member_mean(err * batch.actor_mask)  # the one line that differs: weight 1
        self.step_policy(loss)
        return {"policy_loss": loss.detach()}
