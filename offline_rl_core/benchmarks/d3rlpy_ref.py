"""d3rlpy 2.8 AWAC and BC on the same data and sizes: a reference for training speed.

d3rlpy is the ``bench`` extra (``pip install -e '.[bench]'``); nothing in the runtime
package imports it. ``available()`` says whether it is installed. The timed loop is
``fit()``'s own inner loop (sample a transition batch, ``update``) without its file
logging and progress bar, so d3rlpy is not charged for I/O we skip ourselves.
"""

from __future__ import annotations

import time

import torch

from ..data.interop import d3rlpy_dataset, import_d3rlpy
from ..data.transitions import Transitions
from ..learners.config import TrainConfig

D3RLPY_VERSION = "2.8.1"


def available() -> str | None:
    """d3rlpy's version when importable, else None."""
    try:
        d3rlpy = import_d3rlpy()
    except Exception:
        return None
    return str(d3rlpy.__version__)


def make_algo(algo: str, hidden: int, batch_size: int, lr: float = TrainConfig.lr, beta: float = TrainConfig.beta,
              device: str = "cpu"):
    """d3rlpy's AWAC (twin critics, lam = the chapter's beta) or deterministic BC, with
    ``hidden x hidden`` ReLU encoders like ours."""
    d3rlpy = import_d3rlpy()

    enc = d3rlpy.models.VectorEncoderFactory(hidden_units=[hidden, hidden])
    if algo == "awac":
        cfg = d3rlpy.algos.AWACConfig(
            actor_encoder_factory=enc, critic_encoder_factory=enc, batch_size=batch_size,
            actor_learning_rate=lr, critic_learning_rate=lr, lam=beta, n_critics=2,
        )
    elif algo == "bc":
        cfg = d3rlpy.algos.BCConfig(encoder_factory=enc, batch_size=batch_size, learning_rate=lr,
                                    policy_type="deterministic")
    else:
        raise ValueError(f"no d3rlpy reference for {algo}")
    dev = torch.device(device)
    return cfg.create(device=f"{dev.type}:{dev.index or 0}")


class D3rlpyTrainer:
    """A built d3rlpy learner and its dataset; ``run(steps)`` trains and returns seconds."""

    def __init__(self, algo: str, data: Transitions, hidden: int, batch_size: int, seed: int = 0, device: str = "cpu"):
        d3rlpy = import_d3rlpy()

        d3rlpy.seed(seed)
        self.dataset = d3rlpy_dataset(data)
        self.algo = make_algo(algo, hidden, batch_size, device=device)
        self.algo.build_with_dataset(self.dataset)
        self.batch_size = batch_size

    def run(self, steps: int) -> float:
        t0 = time.perf_counter()
        for _ in range(steps):
            batch = self.dataset.sample_transition_batch(self.batch_size)
            self.algo.update(batch)
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        return time.perf_counter() - t0
