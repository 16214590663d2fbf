"""Where an optional speed layer plugs onto the learners.

The learners are plain torch: a learner's ``update`` is forwards, ``loss.backward()`` and
optimiser steps, and every gradient comes from autograd. A speed layer may register itself
here (``register``) to run the same maths faster on the CPU in two places:

- ``network_forward(net, cfg)``: a faster forward (and backward) for one ``EnsembleMLP``,
  or None where it does not cover that network (then autograd runs it);
- ``step_runner(update, data, threads)``: a faster way to run a learner's ``update`` each
  step (e.g. recorded once and replayed), or None (then ``update`` runs as it is).

The learners never import a speed layer; ``offline_rl_core.fast`` registers itself when it
is imported (``runs`` imports it where it is installed). With none registered the learners
train with autograd alone, on any network shape.
"""

from __future__ import annotations

from typing import Callable, Protocol


class SpeedLayer(Protocol):
    def network_forward(self, net, cfg) -> tuple[Callable, str] | None:
        """(forward(x, weights, biases, tanh_output), a description of its kernels), or None."""

    def step_runner(self, update: Callable, data, threads: int | None) -> Callable | None:
        """A callable taking a step's batch indices, returning the update's losses; or None."""

    def intra_op_threads(self, threads: int | None) -> int:
        """torch's threads per operator call while training with this layer."""


_registered: SpeedLayer | None = None


def register(layer: SpeedLayer | None) -> None:
    """Make ``layer`` the speed layer of every learner built from now on (None: none)."""
    global _registered
    _registered = layer


def registered() -> SpeedLayer | None:
    return _registered
