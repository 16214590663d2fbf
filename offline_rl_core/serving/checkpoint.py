"""The checkpoint format: what a trained policy is on disk, written atomically, validated on load.

A checkpoint is a plain dict saved with ``torch.save`` and loaded with
``torch.load(weights_only=True)`` (tensors, numbers, strings, lists, dicts only):

    format, version, algorithm, obs_dim, act_dim, hidden,
    policy_state   -- Linear weights of obs -> hidden -> hidden -> act (tanh on top)
    obs_mean, obs_std -- input normalisation (identity for the chapter's learners)
    learner_state  -- optional: critic/value weights, for warm starts (``--init``)
    task           -- the task it acts on: ``{task, digest, observation, action, spec}``, the
                      task's layout (name, digest, one label per observation and action value)
                      and its whole spec (``TaskSpec.describe()``); absent: pusher_reach's (every
                      checkpoint written before tasks existed)
    config, seed, dataset_hash, datasets, metrics

It is written atomically (temp file in the same directory, then ``os.replace``), so a
policy node watching the file never reads half a checkpoint; everything ``LoadedPolicy``
multiplies by is checked on load (shapes, finiteness), so a bad file is refused in one line.
"""

from __future__ import annotations

import io
import os
import pickle
import stat
import warnings
import zipfile
from pathlib import Path

import numpy as np
import torch

from ..common.atomic import atomic_path
from ..common.errors import UserError
from ..task.spec import DEFAULT_TASK, TaskSpec, load_task, task_from_dict

CHECKPOINT_FORMAT = "pusher-rl/policy"
CHECKPOINT_VERSION = 1
TASK_FIELDS = ("task", "digest", "observation", "action", "spec")


def task_field(task: TaskSpec) -> dict:
    """What a checkpoint records of its task (``checkpoint["task"]``)."""
    return {**task.layout(), "spec": task.describe()}


def checkpoint_layout(ckpt: dict) -> dict:
    """The task layout a (validated) checkpoint records: its ``task`` field without the spec,
    or pusher_reach's when it records none."""
    recorded = ckpt.get("task")
    if recorded is None:
        return load_task(DEFAULT_TASK).layout()
    return {k: recorded[k] for k in TASK_FIELDS if k != "spec"}


def checkpoint_task(ckpt: dict) -> TaskSpec:
    """The task a (validated) checkpoint acts on: the spec it records, else pusher_reach."""
    recorded = ckpt.get("task")
    return load_task(DEFAULT_TASK) if recorded is None else task_from_dict(recorded["spec"])


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
    return validated_checkpoint(_torch_load(io.BytesIO(bytes(data)), source), source)


def read_torch_file(path: str | os.PathLike) -> dict:
    """A file of ``torch.save`` (tensors and plain values only), checked as a checkpoint's file
    is (not a bag, not truncated, its CRCs); a UserError of one line naming it otherwise."""
    with open(path, "rb") as f:
        return _torch_load(f, str(path))


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


def regular_file_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` cannot be a checkpoint file without opening it (missing, not a regular
    file: a FIFO or a terminal would block a reader), or None."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return f"{path}: no such checkpoint file"
    except OSError as exc:
        return f"{path}: cannot read the checkpoint ({exc.strerror})"
    if not stat.S_ISREG(mode):
        return f"{path}: not a regular file (a FIFO, device or socket); expected a checkpoint file"
    return None


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
        # one open file for the CRC check and the load, whatever renames meanwhile; opened
        # without blocking, so a FIFO or a terminal put in its place is refused, not waited on
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as exc:
        raise UserError(f"{path}: cannot read the checkpoint ({exc.strerror})") from None
    f = os.fdopen(fd, "rb")
    with f:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise UserError(f"{path}: not a regular file (a FIFO, device or socket); expected a checkpoint file")
        return validated_checkpoint(_torch_load(f, path), path)


def validated_checkpoint(ckpt, path) -> dict:
    """``ckpt`` if it is a servable checkpoint (fields, shapes, finite values); a UserError naming ``path`` if not."""
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
    _check_task(ckpt, path)
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


def _check_task(ckpt: dict, path) -> None:
    """The ``task`` field: absent (pusher_reach's), or a layout that fits the policy's sizes
    and a spec that reads as a task of that layout."""
    recorded = ckpt.get("task")
    if recorded is None:
        return
    expected = "a mapping of " + ", ".join(TASK_FIELDS)
    if not isinstance(recorded, dict) or set(recorded) != set(TASK_FIELDS):
        got = sorted(recorded) if isinstance(recorded, dict) else type(recorded).__name__
        raise UserError(f"{path}: checkpoint field 'task' must be {expected}, got {got}")
    for key in ("task", "digest"):
        if not isinstance(recorded[key], str) or not recorded[key]:
            raise UserError(f"{path}: checkpoint field 'task.{key}' must be a non-empty string, got {recorded[key]!r}")
    for key, size in (("observation", ckpt["obs_dim"]), ("action", ckpt["act_dim"])):
        labels = recorded[key]
        if not isinstance(labels, list) or not all(isinstance(v, str) for v in labels) or len(labels) != size:
            raise UserError(f"{path}: checkpoint field 'task.{key}' must be {size} labels "
                            f"(the policy's {'obs_dim' if key == 'observation' else 'act_dim'}), got "
                            f"{len(labels) if isinstance(labels, list) else type(labels).__name__}")
    task = task_from_dict(recorded["spec"], Path(f"{path}: checkpoint field task.spec"))  # its errors name the field
    if task.name != recorded["task"] or list(task.observation_labels()) != recorded["observation"] \
            or list(task.action_labels()) != recorded["action"]:
        raise UserError(f"{path}: checkpoint field 'task': its spec (task {task.name}, obs {task.obs_dim}, "
                        f"action {task.act_dim}) is not the layout it records (task {recorded['task']}, "
                        f"obs {len(recorded['observation'])}, action {len(recorded['action'])})")
