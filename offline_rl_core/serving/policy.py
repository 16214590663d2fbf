"""The checkpoint format and the policy that serves from it.

A checkpoint is a plain dict saved with ``torch.save`` and loaded with
``torch.load(weights_only=True)`` (tensors, numbers, strings, lists, dicts only):

    format, version, algorithm, obs_dim, act_dim, hidden,
    policy_state   -- Linear weights of obs -> hidden -> hidden -> act (tanh on top)
    obs_mean, obs_std -- input normalisation (identity for the chapter's learners)
    learner_state  -- optional: critic/value weights, for warm starts (``--init``)
    config, seed, dataset_hash, datasets, metrics

It is written atomically (temp file in the same directory, then ``os.replace``), so a
policy node watching the file never reads half a checkpoint.
"""

from __future__ import annotations

import io
import os
import pickle
import warnings
import zipfile
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..common.atomic import atomic_path
from ..task.pusher_reach import ACT_DIM, OBS_DIM
from ..common.errors import UserError

CHECKPOINT_FORMAT = "pusher-rl/policy"
CHECKPOINT_VERSION = 1


def save_checkpoint(path: str | os.PathLike, checkpoint: dict) -> Path:
    """Write ``checkpoint`` to ``path`` atomically; returns the path."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        torch.save(checkpoint, f)
        f.flush()
        os.fsync(f.fileno())
    return Path(path)


def checkpoint_to_bytes(checkpoint: dict) -> bytes:
    """A checkpoint as bytes (the ``torch.save`` format), e.g. for a weights message."""
    buf = io.BytesIO()
    torch.save(checkpoint, buf)
    return buf.getvalue()


def checkpoint_from_bytes(data: bytes, source: str) -> dict:
    """``checkpoint_to_bytes`` reversed and validated like a file; ``source`` names it in errors."""
    return _validated(_torch_load(io.BytesIO(bytes(data)), source), source)


def _torch_load(f, source) -> dict:
    problem = _not_a_checkpoint(f)
    try:
        if problem is None:
            _check_zip_crcs(f)
            with warnings.catch_warnings():  # a corrupt file's pickle-protocol notes say nothing the error does not
                warnings.simplefilter("ignore")
                return torch.load(f, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        problem = ("it holds objects other than tensors and plain values" if "weights_only" in str(exc)
                   else "not a torch checkpoint")
    except Exception as exc:  # torch raises many types for corrupt files
        problem = _first_words(exc)
    raise UserError(f"{source}: not a readable pusher-rl checkpoint ({problem})") from None


def _not_a_checkpoint(f) -> str | None:
    """What the file is instead of a torch.save zip, in plain words (None: it may be one)."""
    head = f.read(16)
    size = f.seek(0, io.SEEK_END)
    f.seek(0)
    if size == 0:
        return "the file is empty"
    # bag.storage_sqlite.SQLITE_MAGIC, written out: the policy node loads no bag code
    if head.startswith(b"SQLite format 3\x00"):
        return "an SQLite database, e.g. a rosbag2 .db3 bag, not a torch checkpoint"
    if head.startswith(b"\x89MCAP"):
        return "an MCAP file, e.g. a rosbag2 .mcap bag, not a torch checkpoint"
    if head.startswith(b"PK\x03\x04"):
        return None if zipfile.is_zipfile(f) else "truncated: the torch zip archive ends early"
    if head[:1] == b"\x80":
        return None  # a pickle: torch's legacy format, judged by torch.load
    return "not a torch checkpoint"


def _first_words(exc: BaseException, limit: int = 160) -> str:
    """The first line of ``exc``'s text, cut at a word boundary."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return text if len(text) <= limit else text[:limit].rsplit(" ", 1)[0] + " ..."


def _check_zip_crcs(f) -> None:
    """torch.save writes a zip, but torch.load never checks its CRCs: a flipped bit in the
    weights would load as other weights. Checked here (a legacy non-zip file is left to torch)."""
    if zipfile.is_zipfile(f):
        with zipfile.ZipFile(f) as archive:  # leaves ``f`` open
            bad = archive.testzip()
        if bad is not None:
            raise ValueError(f"damaged: record {bad} fails its CRC check")
    f.seek(0)


def checkpoint_file(path: str | os.PathLike) -> Path:
    """The checkpoint file ``path`` names: a run directory means its policy.pt (the file the trainer replaces)."""
    path = Path(path)
    return path / "policy.pt" if path.is_dir() else path


def load_checkpoint(path: str | os.PathLike) -> dict:
    """Read and validate a checkpoint; a clear ``UserError`` for anything wrong."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such checkpoint file")
    if path.is_dir():
        candidate = checkpoint_file(path)
        if not candidate.exists():
            raise UserError(f"{path}: is a directory without policy.pt; expected a checkpoint file")
        path = candidate
    try:
        f = open(path, "rb")  # one open file for the CRC check and the load, whatever renames meanwhile
    except OSError as exc:
        raise UserError(f"{path}: cannot read the checkpoint ({exc.strerror})") from None
    with f:
        return _validated(_torch_load(f, path), path)


def _validated(ckpt, path) -> dict:
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise UserError(f"{path}: not a pusher-rl checkpoint (expected format '{CHECKPOINT_FORMAT}')")
    if ckpt.get("version") != CHECKPOINT_VERSION:
        raise UserError(f"{path}: checkpoint version {ckpt.get('version')} is not supported (expected {CHECKPOINT_VERSION})")
    for key in ("obs_dim", "act_dim", "hidden", "policy_state", "algorithm"):
        if key not in ckpt:
            raise UserError(f"{path}: checkpoint lacks the field '{key}'")
    for key in ("obs_dim", "act_dim", "hidden"):
        if type(ckpt[key]) is not int or ckpt[key] < 1:
            raise UserError(f"{path}: checkpoint field '{key}' is {ckpt[key]!r}, expected a positive integer")
    _check_policy_state(ckpt, path)
    _check_normalisation(ckpt, path)
    log_std = ckpt.get("exploration_log_std")
    if log_std is not None and (not torch.is_tensor(log_std) or log_std.numel() != int(ckpt["act_dim"])
                                or not bool(torch.isfinite(log_std).all())):
        raise UserError(f"{path}: exploration_log_std must be {ckpt['act_dim']} finite values")
    return ckpt


def _check_policy_state(ckpt: dict, path) -> None:
    """Every tensor ``LoadedPolicy`` multiplies by: present, the shape its layer needs, finite."""
    state = ckpt["policy_state"]
    if not isinstance(state, dict):
        raise UserError(f"{path}: policy_state is not a dict of tensors")
    hidden, obs_dim, act_dim = ckpt["hidden"], ckpt["obs_dim"], ckpt["act_dim"]
    expected = {
        "0.weight": (hidden, obs_dim), "0.bias": (hidden,),
        "2.weight": (hidden, hidden), "2.bias": (hidden,),
        "4.weight": (act_dim, hidden), "4.bias": (act_dim,),
    }
    for name, shape in expected.items():
        tensor = state.get(name)
        if name not in state:
            raise UserError(f"{path}: policy weight '{name}' is missing (expected shape {shape})")
        if not torch.is_tensor(tensor) or tuple(tensor.shape) != shape:
            got = tuple(tensor.shape) if torch.is_tensor(tensor) else type(tensor).__name__
            raise UserError(f"{path}: policy weight '{name}' has shape {got}, expected {shape}")
    for name, tensor in state.items():
        if name not in expected:
            raise UserError(f"{path}: policy_state has an unexpected entry '{name}' (expected {', '.join(expected)})")
        if not tensor.is_floating_point() or not bool(torch.isfinite(tensor).all()):
            raise UserError(f"{path}: policy weight '{name}' is not a finite tensor")


def _check_normalisation(ckpt: dict, path) -> None:
    """obs_mean/obs_std: both absent, or obs_dim finite values each, every std > 0."""
    mean, std = ckpt.get("obs_mean"), ckpt.get("obs_std")
    if mean is None and std is None:
        return
    for name, value in (("obs_mean", mean), ("obs_std", std)):
        try:
            values = np.asarray(value.detach().cpu() if torch.is_tensor(value) else value, dtype=np.float64)
        except (TypeError, ValueError):
            values = np.full(1, np.nan)
        if values.shape != (ckpt["obs_dim"],) or not np.isfinite(values).all():
            raise UserError(f"{path}: {name} must be obs_dim={ckpt['obs_dim']} finite values "
                            f"(or both obs_mean and obs_std absent)")
        if name == "obs_std" and not (values > 0).all():
            raise UserError(f"{path}: obs_std must be > 0 everywhere (it divides each observation)")


def policy_sequential(obs_dim: int, hidden: int, act_dim: int) -> nn.Sequential:
    """A single policy as ordinary layers (the form exported to ONNX; the checkpoint's
    ``policy_state`` loads into it); tanh is applied by the caller (``LoadedPolicy.torch_module``)."""
    return nn.Sequential(
        nn.Linear(obs_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, act_dim)
    )


class LoadedPolicy:
    """A trained policy ready to act: ``act(obs) -> actions`` in [-1, 1].

    Inference runs in numpy (float32): for one observation that is several times
    faster than a torch call, which is what the policy node serves.
    """

    def __init__(self, checkpoint: dict, source: str = "<memory>"):
        self.checkpoint = checkpoint
        self.source = source
        self.algorithm = str(checkpoint["algorithm"])
        self.obs_dim = int(checkpoint["obs_dim"])
        self.act_dim = int(checkpoint["act_dim"])
        self.hidden = int(checkpoint["hidden"])
        state = checkpoint["policy_state"]
        # Stored transposed once so a row of observations multiplies directly.
        self._w = [state[f"{i}.weight"].detach().float().numpy().T.copy() for i in (0, 2, 4)]
        self._b = [state[f"{i}.bias"].detach().float().numpy().copy() for i in (0, 2, 4)]
        # the online learner's Gaussian: exploration samples tanh(mean + std * eps)
        log_std = checkpoint.get("exploration_log_std")
        self.exploration_log_std = None if log_std is None else np.asarray(log_std, np.float32).reshape(-1)
        # the online learner's weights carry their version; a trained checkpoint has none
        self.versioned = "weights_version" in checkpoint
        self.weights_version = int(checkpoint.get("weights_version", 0) or 0)
        mean = checkpoint.get("obs_mean")
        std = checkpoint.get("obs_std")
        self._obs_mean = None if mean is None else np.asarray(mean, dtype=np.float32)
        self._obs_std = None if std is None else np.asarray(std, dtype=np.float32)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """obs (obs_dim,) or (N, obs_dim) -> float32 actions of the same leading shape."""
        return np.tanh(self.pre_tanh(obs)).astype(np.float32, copy=False)

    def sample(self, obs: np.ndarray, rng: np.random.Generator, log_std: np.ndarray | float | None = None) -> np.ndarray:
        """An exploration action: tanh(mean + std * eps), eps ~ N(0, 1) from ``rng``, with
        the checkpoint's learnt std (or ``log_std``); in [-1, 1] like ``act``."""
        log_std = self.exploration_log_std if log_std is None else log_std
        mean = self.pre_tanh(obs)
        if log_std is None:
            return np.tanh(mean).astype(np.float32, copy=False)
        eps = rng.standard_normal(mean.shape).astype(np.float32)
        return np.tanh(mean + np.exp(np.asarray(log_std, np.float32)) * eps).astype(np.float32, copy=False)

    def pre_tanh(self, obs: np.ndarray) -> np.ndarray:
        """The network's output before the tanh: float32, shaped like ``act``'s."""
        x = np.asarray(obs, dtype=np.float32)
        single = x.ndim == 1
        if single:
            x = x[None, :]
        if x.shape[-1] != self.obs_dim:
            raise ValueError(f"observation has {x.shape[-1]} values, the policy expects {self.obs_dim}")
        if self._obs_mean is not None:
            x = (x - self._obs_mean) / self._obs_std
        h = np.maximum(x @ self._w[0] + self._b[0], 0.0)
        h = np.maximum(h @ self._w[1] + self._b[1], 0.0)
        y = (h @ self._w[2] + self._b[2]).astype(np.float32, copy=False)
        return y[0] if single else y

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.act(obs)

    def torch_module(self) -> torch.nn.Module:
        """The policy as a torch module (obs -> tanh action), e.g. for ONNX export."""
        net = policy_sequential(self.obs_dim, self.hidden, self.act_dim)
        net.load_state_dict({k: v.float() for k, v in self.checkpoint["policy_state"].items()})
        mean = self._obs_mean
        std = self._obs_std

        class TanhPolicy(torch.nn.Module):
            def __init__(self):
                super().__init__()
                self.net = net
                self.register_buffer("obs_mean", torch.as_tensor(mean if mean is not None else np.zeros(net[0].in_features, np.float32)))
                self.register_buffer("obs_std", torch.as_tensor(std if std is not None else np.ones(net[0].in_features, np.float32)))

            def forward(self, obs: torch.Tensor) -> torch.Tensor:
                return torch.tanh(self.net((obs - self.obs_mean) / self.obs_std))

        return TanhPolicy().eval()


def load_policy(path: str | os.PathLike, obs_dim: int = OBS_DIM, act_dim: int = ACT_DIM) -> LoadedPolicy:
    """Load a checkpoint for acting; refuses one whose dims do not match the task."""
    return policy_for_task(load_checkpoint(path), path, obs_dim, act_dim)


def policy_for_task(ckpt: dict, source, obs_dim: int = OBS_DIM, act_dim: int = ACT_DIM) -> LoadedPolicy:
    """A validated checkpoint as a policy, refused when its dims do not match the task."""
    if int(ckpt["obs_dim"]) != obs_dim or int(ckpt["act_dim"]) != act_dim:
        raise UserError(
            f"{source}: checkpoint has obs_dim={ckpt['obs_dim']}, act_dim={ckpt['act_dim']}; "
            f"the pusher task needs obs_dim={obs_dim}, act_dim={act_dim}"
        )
    return LoadedPolicy(ckpt, source=str(source))
