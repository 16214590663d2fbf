"""Resume points: a learner's whole training state as tensors, written atomically.

What a step can change is gathered generically from the learner's attributes (and its
helpers', e.g. ``critic.opt``): modules, loose parameters (a log-std), optimisers and
random generators. Restored into a freshly built learner before its first step, the run
continues with the same bytes as one that was never stopped: eager and replayed steps
give the same results (``traced.py``), and nothing else carries state.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from ..common.atomic import atomic_path, remove_partial_writes
from ..common.errors import UserError
from .state import named

RESUME_FORMAT = "pusher-rl/resume"


def _named(learner, kind) -> dict:
    """The learner's state of type ``kind``, and its helpers' one level down, by dotted name."""
    return named(learner, kind, depth=1)


def learner_training_state(learner) -> dict:
    return {
        "modules": {n: m.state_dict() for n, m in _named(learner, torch.nn.Module).items()},
        "params": {n: p.detach().clone() for n, p in _named(learner, torch.nn.Parameter).items()},
        "optimizers": {n: o.state_dict() for n, o in _named(learner, torch.optim.Optimizer).items()},
        "generators": {n: g.get_state() for n, g in _named(learner, torch.Generator).items()},
    }


def load_learner_training_state(learner, state: dict) -> None:
    with torch.no_grad():
        for name, module in _named(learner, torch.nn.Module).items():
            module.load_state_dict(state["modules"][name])
        for name, p in _named(learner, torch.nn.Parameter).items():
            p.copy_(state["params"][name])
    for name, opt in _named(learner, torch.optim.Optimizer).items():
        opt.load_state_dict(state["optimizers"][name])
    for name, gen in _named(learner, torch.Generator).items():
        gen.set_state(state["generators"][name])


def save_atomic(path: str | os.PathLike, state: dict) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        torch.save(state, f)
        f.flush()
        os.fsync(f.fileno())


@dataclass
class ResumePoints:
    """Where and how often a training run writes its resume point, and whether to start
    from one. ``every_s`` bounds what a kill loses (in wall time)."""

    path: Path
    every_s: float = 1.0
    resume: bool = False
    _last: float = 0.0

    def due(self) -> bool:
        return time.monotonic() - self._last >= self.every_s

    def write(self, state: dict) -> None:
        save_atomic(self.path, {"format": RESUME_FORMAT, **state})
        self._last = time.monotonic()

    def read(self) -> dict | None:
        """The resume point to start from (None: start afresh). Called as a run starts, so
        it first clears the temp files of writes a kill interrupted."""
        remove_partial_writes(self.path)
        if not self.resume or not self.path.exists():
            return None
        try:
            state = torch.load(self.path, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - torch raises many types for a damaged file
            raise UserError(f"{self.path}: unreadable resume point ({str(exc).strip().splitlines()[0][:120]}); "
                             "delete it to start over") from None
        if not isinstance(state, dict) or state.get("format") != RESUME_FORMAT:
            raise UserError(f"{self.path}: not a pusher-rl resume point")
        return state

    def done(self) -> None:
        self.path.unlink(missing_ok=True)
