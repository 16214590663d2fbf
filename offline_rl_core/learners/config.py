"""Training configuration: one dataclass whose fields are the `offline-rl train` flags.

Defaults are the chapter's hyper-parameters (and Kostrikov et al.'s for IQL).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

ALGORITHMS = ("bc", "filtered_bc", "awac", "iql", "naive", "sac")


@dataclass
class TrainConfig:
    algo: str = "awac"
    steps: int = 8000
    batch_size: int = 256
    hidden: int = 256
    lr: float = 3e-4
    gamma: float = 0.99
    tau: float = 0.005  # Polyak rate of the target critics
    # AWAC
    beta: float = 0.3
    weight_clip: float = 20.0
    # IQL
    expectile: float = 0.7
    temperature: float = 3.0
    max_weight: float = 100.0
    # SAC (the online learner): entropy weight, fixed unless target_entropy is set; the
    # Gaussian's initial log-std; weight of the squared error to a person's actions
    alpha: float = 0.01
    target_entropy: float | None = None
    init_log_std: float = -1.0
    bc_weight: float = 1.0
    # filtered BC: keep the top fraction of episodes by return
    filter_top_frac: float = 0.1
    # corrections: share of each batch drawn from correction transitions (None = uniform)
    correction_ratio: float | None = None
    # how often (steps) losses are read back and progress is reported
    log_every: int = 100
    # torch intra-op threads while training. Chapter-size MLPs gain little from more,
    # and when other processes share the cores (ROS nodes, tests) OpenMP's spinning
    # threads can slow a step fifty-fold. Use the cores with whole runs instead
    # (``learners/parallel.py``, ``offline-rl experiment --workers``).
    threads: int = 1
    # False (default): the 256x256 hidden layer's matmuls in bf16 where the CPU has native
    # bf16 (AMX / AVX512-BF16), about 1.4x faster for AWAC here; fp32 elsewhere.
    # True: fp32 everywhere, the same numbers whatever the CPU's bf16 support.
    # Both are byte-identical run to run for a seed on one machine.
    deterministic: bool = False
    # "cpu", or "cuda" / "cuda:N" for an NVIDIA GPU (fp32; the hidden-layer bf16 above is
    # the CPU's). Nothing requires a GPU.
    device: str = "cpu"
    # On CUDA, record the whole update once as a CUDA graph and replay it each step:
    # chapter-size networks are launch-bound on a GPU (a step is a few hundred tiny
    # kernels), and one replay replaces all of those launches.
    cuda_graph: bool = True

    def __post_init__(self) -> None:
        if self.algo not in ALGORITHMS:
            raise ValueError(f"unknown algorithm '{self.algo}'; expected one of {', '.join(ALGORITHMS)}")
        for name in ("steps", "batch_size", "hidden", "log_every", "threads"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 < self.filter_top_frac <= 1.0:
            raise ValueError(f"filter_top_frac must be in (0, 1], got {self.filter_top_frac}")
        if self.alpha <= 0:
            raise ValueError(f"alpha must be > 0, got {self.alpha}")
        if self.bc_weight < 0:
            raise ValueError(f"bc_weight must be >= 0, got {self.bc_weight}")
        if self.correction_ratio is not None and not 0.0 <= self.correction_ratio <= 1.0:
            raise ValueError(f"correction_ratio must be in [0, 1], got {self.correction_ratio}")
        check_device(self.device)

    def to_dict(self) -> dict:
        return asdict(self)


def check_device(device: str) -> None:
    """Raise ValueError unless ``device`` names a torch device this machine has."""
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(f"device: expected 'cpu', 'cuda' or 'cuda:N', got '{device}'") from None
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"device: expected 'cpu', 'cuda' or 'cuda:N', got '{device}'")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {device}: no CUDA GPU is available here (torch {torch.__version__}); use --device cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"device {device}: this machine has {torch.cuda.device_count()} CUDA device(s)")
