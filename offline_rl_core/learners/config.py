"""Training configuration: one dataclass whose fields are the `offline-rl train` flags
(each field's help text is its flag's, see ``training_run.add_train_arguments``).

Defaults are the chapter's hyper-parameters (and Kostrikov et al.'s for IQL).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

from .schedule import SCHEDULES

ALGORITHMS = ("bc", "filtered_bc", "awac", "iql", "naive", "sac")
# SAC's log-std is clamped to these bounds (outside them it stops learning)
LOG_STD_MIN, LOG_STD_MAX = -5.0, 1.0


def _opt(default, help: str, group: str = "hyper-parameters", kind: type | None = None):
    """A field that is also an ``offline-rl train`` flag (``--name-with-dashes``);
    ``kind``: the flag's type where the default (None) does not say it."""
    return field(default=default, metadata={"help": help, "group": group, "kind": kind})


@dataclass
class TrainConfig:
    algo: str = _opt("awac", "learner", "run")
    steps: int = _opt(8000, "gradient steps", "run")
    batch_size: int = _opt(256, "batch size")
    hidden: int = _opt(256, "hidden layer width")
    lr: float = _opt(3e-4, "Adam learning rate")
    lr_schedule: str = _opt("constant", "learning rate over the run: constant, or cosine (from --lr down to 0 at the last step)")
    gamma: float = _opt(0.99, "discount")
    tau: float = _opt(0.005, "Polyak rate of the target critics")
    beta: float = _opt(0.3, "AWAC temperature")
    weight_clip: float = _opt(20.0, "AWAC weight clip")
    expectile: float = _opt(0.7, "IQL expectile")
    temperature: float = _opt(3.0, "IQL inverse temperature")
    max_weight: float = _opt(100.0, "IQL weight clip")
    # SAC is the online (HIL-SERL) learner; it trains offline too
    alpha: float = _opt(0.01, "SAC entropy weight (fixed unless --target-entropy is set)")
    target_entropy: float | None = _opt(None, "SAC: tune the entropy weight toward this entropy")
    init_log_std: float = _opt(-1.0, "SAC: the Gaussian policy's initial log-std")
    bc_weight: float = _opt(3.0, "SAC: weight of the squared error to a person's (source human) actions")
    normalize_obs: bool = _opt(
        False, "train on z-scored observations (mean and std of the rows sampled); the checkpoint folds them into "
               "the networks' first layers, so it takes raw observations as any other")
    filter_top_frac: float = _opt(0.1, "filtered BC: share of best episodes by return")
    filter_by: str = _opt("return", "filtered BC: keep the --filter-top-frac best episodes by return (return), "
                                    "or the episodes that end at the goal (goal)")
    correction_ratio: float | None = _opt(
        None, "share of each batch drawn from correction runs (policy/human transitions); default: uniform")
    log_every: int = _opt(100, "steps between progress reports (and loss read-backs)", "run")
    # A chapter-size step's products are too small to split over threads (OpenMP's
    # fork/join costs about what it saves, and on a shared machine its spinning threads
    # stall), so the threads run different operator calls of the recorded step side by
    # side instead (``traced.py``); each call stays single-threaded.
    threads: int | None = _opt(
        None, "CPU threads one training step runs on (default: as many of this machine's free cores as the "
              "step's measured shape can use); with the C++ step replay (built by make setup) any number gives "
              "the same bytes. Without it (no compiler, or PUSHER_RL_STEP=python/autograd) the default is one "
              "thread, which trains the same bytes as the C++ replay; a number given there trains its own",
        "run", kind=int)
    deterministic: bool = _opt(
        False, "fp32 everywhere. The default runs the hidden layer in bf16 where that measured clearly faster on "
               "this CPU (kernel_choice; the choice is cached per machine in ~/.cache/pusher-rl, so later runs make "
               "the same one); the checkpoint records which (its 'kernels')", "run")
    device: str = _opt("cpu", "cpu, or cuda / cuda:N to train on an NVIDIA GPU; evaluation stays on the CPU", "run")
    # A chapter-size step is a few hundred tiny kernels: on a GPU, one replayed graph
    # replaces all of those launches.
    cuda_graph: bool = _opt(True, "on CUDA, replay each step as one recorded CUDA graph", "run")

    def __post_init__(self) -> None:
        # Messages name the flag (``--gamma``): the CLI and the trainer node show them as they are.
        if self.algo not in ALGORITHMS:
            raise ValueError(f"--algo: unknown algorithm '{self.algo}'; expected one of {', '.join(ALGORITHMS)}")
        for name in ("steps", "batch_size", "hidden", "log_every", "threads"):
            if getattr(self, name) is not None and int(getattr(self, name)) < 1:
                raise ValueError(f"{_flag(name)} must be >= 1, got {getattr(self, name)}")
        for name, choices in CHOICES.items():
            if getattr(self, name) not in choices:
                raise ValueError(f"{_flag(name)}: expected one of {', '.join(choices)}, got '{getattr(self, name)}'")
        for name, (low, high, low_open, high_open) in {**RANGES, "init_log_std": (LOG_STD_MIN, LOG_STD_MAX, False, False)}.items():
            value = getattr(self, name)
            if value is not None:
                _check_range(name, value, low, high, low_open, high_open)
        try:
            check_device(self.device)
        except ValueError as exc:
            raise ValueError(f"--{exc}") from None

    def to_dict(self) -> dict:
        return asdict(self)


CHOICES = {"lr_schedule": SCHEDULES, "filter_by": ("return", "goal")}

# (low, high, low excluded, high excluded) of each float field; every one must also be finite.
# A NaN or a value out of these ranges trains a diverging or meaningless learner.
RANGES = {
    "lr": (0.0, math.inf, True, False),
    "gamma": (0.0, 1.0, False, False),
    "tau": (0.0, 1.0, True, False),
    "beta": (0.0, math.inf, True, False),
    "weight_clip": (0.0, math.inf, True, False),
    "expectile": (0.0, 1.0, True, True),
    "temperature": (0.0, math.inf, False, False),
    "max_weight": (0.0, math.inf, True, False),
    "alpha": (0.0, math.inf, True, False),
    "target_entropy": (-math.inf, math.inf, False, False),
    "bc_weight": (0.0, math.inf, False, False),
    "filter_top_frac": (0.0, 1.0, True, False),
    "correction_ratio": (0.0, 1.0, False, False),
}


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _check_range(name: str, value: float, low: float, high: float, low_open: bool, high_open: bool) -> None:
    value = float(value)
    inside = math.isfinite(value) and (value > low if low_open else value >= low) and \
        (value < high if high_open else value <= high)
    if inside:
        return
    if math.isinf(high):
        expected = f"> {low:g}" if low_open else f">= {low:g}"
        expected = "finite" if math.isinf(low) else f"finite and {expected}"
    else:
        expected = f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    raise ValueError(f"{_flag(name)} must be {expected}, got {value:g}")


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
