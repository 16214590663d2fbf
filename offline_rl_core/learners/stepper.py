"""How one gradient step is run: as it is, by a speed layer on the CPU, a CUDA graph on a GPU.

A learner's ``update`` is the same Python on every path. On the CPU a registered speed
layer may run it (``acceleration``: ``offline_rl_core.fast`` records it once and replays
it); otherwise ``update`` runs every step. On CUDA, chapter-size networks are bound by kernel
launches, not arithmetic, and Python issues them more slowly than the GPU runs them:
``CudaGraphStep`` records the whole step (batch gather, forwards, backwards, both Adam
steps, Polyak) once and then replays it with a single launch per step.
"""

from __future__ import annotations

from typing import Callable

import torch

from ..common.machine import available_cores
from . import acceleration
from .data import MemberData

# Eager steps before the capture: Adam creates its state and cuBLAS its workspaces
# on first use, and neither may happen inside a capture. They are real training
# steps: the run's results do not depend on when the capture happens.
CUDA_CAPTURE_AFTER_STEPS = 3


class EagerStep:
    def __init__(self, update: Callable, data: MemberData):
        self.update, self.data = update, data

    def __call__(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.update(self.data.gather(idx))


class CudaGraphStep:
    """``update(data.gather(idx))`` recorded as a CUDA graph after ``CUDA_CAPTURE_AFTER_STEPS``.

    The graph reads the batch indices from one static tensor, so each step is a copy
    of the next indices into it and one replay. The returned losses are the graph's
    own output tensors, overwritten by the next replay: read them before stepping on
    (the training loop reads them at once, every ``log_every`` steps).
    """

    def __init__(self, update: Callable, data: MemberData, idx_shape: tuple[int, int], device: torch.device):
        self.update, self.data, self.device = update, data, device
        self.static_idx = torch.zeros(idx_shape, dtype=torch.long, device=device)
        self.graph: torch.cuda.CUDAGraph | None = None
        self.outputs: dict[str, torch.Tensor] = {}
        self.eager_steps = 0

    def __call__(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        self.static_idx.copy_(idx)
        if self.graph is None:
            if self.eager_steps < CUDA_CAPTURE_AFTER_STEPS:
                self.eager_steps += 1
                return self._eager_on_side_stream()
            self.graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(self.graph):  # records; runs nothing
                self.outputs = self.update(self.data.gather(self.static_idx))
        self.graph.replay()
        return self.outputs

    def _eager_on_side_stream(self) -> dict[str, torch.Tensor]:
        # warm-up off the default stream, as torch's graph-capture recipe asks
        main = torch.cuda.current_stream(self.device)
        side = torch.cuda.Stream(self.device)
        side.wait_stream(main)
        with torch.cuda.stream(side):
            out = self.update(self.data.gather(self.static_idx))
        main.wait_stream(side)
        return out


_process_default: int | None = None  # set in processes that share the cores with others


def set_default_threads(n: int | None) -> None:
    """Threads for steps whose config leaves them to the default, in this process (the
    experiment's worker processes: one each, the cores go to the processes)."""
    global _process_default
    _process_default = n


def step_threads(threads: int | None) -> int:
    """The threads a CPU training step may run on: ``threads``, or by default this
    process's cores (its CPU affinity); see ``chooses_threads``."""
    if threads is not None:
        return max(1, int(threads))
    if _process_default is not None:
        return _process_default
    return max(1, available_cores())


def chooses_threads(threads: int | None) -> bool:
    """By default the replay uses only as many of ``step_threads`` as the step's timed
    calls say pay (its work over its longest chain); a number given is used as it is."""
    return threads is None and _process_default is None


def intra_op_threads(threads: int | None) -> int:
    """torch's own threads per operator call while training: one by default, a number
    given as it is (each call split over them, which orders its sums otherwise, so each
    number trains its own bytes); a speed layer may say otherwise for its own steps."""
    layer = acceleration.registered()
    if layer is not None:
        return layer.intra_op_threads(threads)
    return 1 if threads is None else max(1, int(threads))


def make_step(update: Callable, data: MemberData, idx_shape: tuple[int, int], device: str, cuda_graph: bool,
              threads: int | None = None):
    """The step runner for ``device``: a CUDA graph on CUDA (unless ``cuda_graph`` is
    False); on the CPU the registered speed layer's runner, where it gives one, else
    ``update`` itself every step."""
    dev = torch.device(device)
    if dev.type == "cuda":
        if not cuda_graph:
            return EagerStep(update, data)
        if dev.index is None:
            dev = torch.device("cuda", torch.cuda.current_device())
        return CudaGraphStep(update, data, idx_shape, dev)
    layer = acceleration.registered()
    runner = layer.step_runner(update, data, threads) if layer is not None else None
    return runner if runner is not None else EagerStep(update, data)
