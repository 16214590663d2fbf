"""Learning-rate schedules, applied to every optimiser of a learner.

The recorded step (``traced.py``) replays the exact operator calls of one update, so a
Python float learning rate would be frozen into the recording. A schedule therefore
turns each optimiser group's rate into a one-element tensor (fused Adam takes it as
is) and writes the rate for the next step into that tensor before the step: the
replay reads it like any other tensor, and eager, Python and C++ steps stay the same
bytes. The rate is a function of the step number alone, so a resumed run continues
the same curve.
"""

from __future__ import annotations

import math

import torch

from .state import optimizers_of

SCHEDULES = ("constant", "cosine")


def lr_factor(schedule: str, step: int, total: int) -> float:
    """The multiplier of the base rate at ``step`` (1-based) of ``total`` steps.

    cosine: from 1 at the first step down to near 0 at the last (Loshchilov & Hutter's
    SGDR without restarts), so the run ends in small steps around where it arrived."""
    if schedule == "constant":
        return 1.0
    if schedule == "cosine":
        return 0.5 * (1.0 + math.cos(math.pi * (step - 1) / max(total, 1)))
    raise ValueError(f"unknown lr schedule '{schedule}'; expected one of {', '.join(SCHEDULES)}")


class LearningRates:
    """Drives the learning rates of ``learner``'s optimisers along ``schedule``."""

    def __init__(self, learner, schedule: str, total: int):
        self.schedule, self.total = schedule, total
        self.groups: list[tuple[torch.Tensor, float]] = []  # (the group's rate tensor, its base rate)
        if schedule == "constant":
            return  # the chapter's learners, untouched: rates stay Python floats
        for opt in optimizers_of(learner):
            for group in opt.param_groups:
                base = float(group.setdefault("base_lr", float(group["lr"])))
                device = group["params"][0].device
                if not isinstance(group["lr"], torch.Tensor):
                    group["lr"] = torch.tensor(base, dtype=torch.float32, device=device)
                self.groups.append((group["lr"], base))

    def at(self, step: int) -> None:
        """Set the rates for ``step`` (1-based)."""
        if not self.groups:
            return
        factor = lr_factor(self.schedule, step, self.total)
        for rate, base in self.groups:
            rate.fill_(base * factor)
