"""The optional speed layer: the learners' maths, run faster on the CPU.

Importing this package registers it onto the learners (``learners.acceleration``); the
learners never import it, and train with plain autograd when this folder is absent. It
changes how a step runs, never what it computes:

- ``mlp_kernels``: the ensemble MLP's forward and backward written out by hand (members
  one by one, the hidden layer on the kernels ``kernel_choice`` measured fastest on this
  CPU). Before a network uses them they are checked against that network's own autograd
  forward on its shape (``network_forward``); a network they do not match runs with autograd.
- ``traced``: a learner's ``update`` recorded once as its exact operator calls and replayed
  every later step, in C++ (``graph_runner``, ``csrc/``) where it builds, else in Python.
"""

from __future__ import annotations

from ..learners import acceleration
from ..learners.stepper import chooses_threads, step_threads
from . import kernel_choice, mlp_kernels, traced


class FastPath:
    """The speed layer as ``learners.acceleration`` asks for it."""

    def network_forward(self, net, cfg):
        if not mlp_kernels.covers(net):
            return None
        kernels = kernel_choice.choose(cfg.deterministic, cfg.hidden, cfg.batch_size, self.intra_op_threads(cfg.threads))
        hidden = mlp_kernels.HiddenLayer(kernels)
        why_not = mlp_kernels.disagreement_with_autograd(net, hidden)
        if why_not is not None:
            traced.notice(f"a {net.in_dim}->{net.hidden}->{net.out_dim} network trains with autograd: "
                          f"the hand-written kernels {why_not}")
            return None

        def forward(x, weights, biases, tanh_output):
            return mlp_kernels.ensemble_mlp(x, weights, biases, tanh_output, hidden)

        return forward, kernels.describe()

    def step_runner(self, update, data, threads):
        mode = traced.step_mode()
        if mode == "autograd":
            return None
        return traced.RecordedStep(update, data, mode, step_threads(threads), chooses_threads(threads))

    def intra_op_threads(self, threads: int | None) -> int:
        """One thread per operator call by default, and always under the C++ replay, which
        spreads the calls over the step's threads instead: then every path (C++ replay,
        Python replay, plain autograd) trains the same bytes. A number given runs eager and
        Python-replayed steps on that many (each call split over them, which changes how its
        sums are ordered, so each number its own bytes)."""
        if threads is None or int(threads) <= 1:
            return 1
        if traced.step_mode() in ("python", "autograd"):
            return int(threads)
        from . import graph_runner

        return 1 if graph_runner.unavailable_reason() is None else int(threads)


acceleration.register(FastPath())
