"""Offline learners: BC, filtered BC, AWAC, IQL and naive max-Q, one module each,
sharing the MLP (``networks``), the data/sampler (``data``) and the loop (``loop``)."""

from .config import ALGORITHMS, TrainConfig
from .loop import LEARNERS, Progress, TrainResult, train, train_seeds

__all__ = ["ALGORITHMS", "LEARNERS", "Progress", "TrainConfig", "TrainResult", "train", "train_seeds"]
