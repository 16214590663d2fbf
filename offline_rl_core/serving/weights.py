"""The weights message: how the online learner hands a new policy to the acting policy node.

A weights version travels as a ``std_msgs/UInt8MultiArray`` whose layout is labelled
``WEIGHTS_LABEL``. Its bytes are signed raw tensors, never a pickle:

    MAGIC (8 bytes) | header length (uint32, little-endian) | header (JSON, UTF-8)
    | payload: the tensors back to back, float32 little-endian, C order | Ed25519 signature (64 bytes)

The header names the session the weights were signed for, the checkpoint's plain fields
(``SCALAR_FIELDS``), the task the weights act on (the checkpoint's ``task`` field: the
policy node refuses weights of another task than its own) and each tensor's name and shape,
in payload order. The signature covers
everything before it, so nothing of a message is parsed before it is known to come from this
session's learner (``signing``). Then, before a byte is allocated for a tensor: the header's
size, every field's type and range, every tensor's shape against the one its layer needs
(from ``obs_dim``, ``act_dim``, ``hidden``, each bounded), and that the shapes cover the
payload exactly (no stride, no gap, no overlap: a 2 KB message cannot stand for a
256 MiB layer). Unversioned weights are refused. The decoded checkpoint is then validated
as a checkpoint file is (finite values, ``checkpoint.validated_checkpoint``).
"""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import torch

from ..common.errors import UserError
from ..common.rejections import Rejection
from ..task.spec import DEFAULT_TASK, TaskSpec
from .checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, validated_checkpoint
from .policy import LoadedPolicy, policy_for_task
from .signing import SIGNATURE_BYTES, Signer, Verifier

WEIGHTS_LABEL = "pusher-rl/weights"  # the weights message's layout label: what its bytes are
WEIGHTS_FORMAT = "pusher-rl/weights"
MAGIC = b"PRLWTS\x00\x01"  # this wire format, version 1
DTYPE = "<f4"
MAX_HEADER_BYTES = 64 << 10  # the task's description included
MAX_WIDTH = 4096  # obs_dim, act_dim, hidden: wider than any policy served here
MAX_PAYLOAD_BYTES = 32 << 20
MAX_MESSAGE_BYTES = len(MAGIC) + 4 + MAX_HEADER_BYTES + MAX_PAYLOAD_BYTES + SIGNATURE_BYTES
MAX_WEIGHTS_VERSION = 2**31 - 1  # a version a year of 1 Hz versions never reaches
MAX_COUNT = 2**53  # counts and seeds: exact in a JSON reader's double

# The checkpoint's plain fields a message carries, with the type each must have.
SCALAR_FIELDS = {
    "algorithm": str, "obs_dim": int, "act_dim": int, "hidden": int, "weights_version": int,
    "trained_through": int, "updates": int, "seed": int, "cut_unix": float,
}
REQUIRED_FIELDS = ("algorithm", "obs_dim", "act_dim", "hidden", "weights_version")
_HEAD = struct.Struct("<I")


class WeightsRefused(Exception):
    """A weights message that must not act; ``rejection`` says why (its reason is counted)."""

    def __init__(self, rejection: Rejection):
        super().__init__(str(rejection))
        self.rejection = rejection


def serving_part(checkpoint: dict) -> dict:
    """What acting needs: the policy, its exploration std, dims, task and provenance."""
    keep = ("format", "version", "algorithm", "obs_dim", "act_dim", "hidden", "policy_state", "obs_mean", "obs_std",
            "exploration_log_std", "task", "weights_version", "trained_through", "updates", "seed", "cut_unix")
    return {k: checkpoint[k] for k in keep if k in checkpoint}


def expected_tensors(obs_dim: int, act_dim: int, hidden: int) -> dict[str, tuple[int, ...]]:
    """Every tensor a message may carry and the shape the policy needs it in."""
    return {
        "policy_state.0.weight": (hidden, obs_dim), "policy_state.0.bias": (hidden,),
        "policy_state.2.weight": (hidden, hidden), "policy_state.2.bias": (hidden,),
        "policy_state.4.weight": (act_dim, hidden), "policy_state.4.bias": (act_dim,),
        "exploration_log_std": (act_dim,), "obs_mean": (obs_dim,), "obs_std": (obs_dim,),
    }


OPTIONAL_TENSORS = ("exploration_log_std", "obs_mean", "obs_std")


def encode_weights(checkpoint: dict, signer: Signer) -> bytes:
    """A weights version (a checkpoint holding at least the policy) as a signed message."""
    fields = {}
    for name, kind in SCALAR_FIELDS.items():
        value = checkpoint.get(name)
        if value is not None:
            fields[name] = float(value) if kind is float else kind(value)
    tensors = {f"policy_state.{k}": v for k, v in checkpoint["policy_state"].items()}
    for name in OPTIONAL_TENSORS:  # vectors, whatever shape the learner keeps them in
        if checkpoint.get(name) is not None:
            tensors[name] = torch.as_tensor(checkpoint[name]).reshape(-1)
    arrays = [(name, np.ascontiguousarray(torch.as_tensor(t).detach().cpu().numpy(), dtype=DTYPE))
              for name, t in tensors.items()]
    head = {"format": WEIGHTS_FORMAT, "session": signer.session, "dtype": DTYPE, "fields": fields,
            "tensors": [[name, list(a.shape)] for name, a in arrays]}
    if checkpoint.get("task") is not None:
        head["task"] = checkpoint["task"]
    header = json.dumps(head, separators=(",", ":")).encode()
    body = b"".join([MAGIC, _HEAD.pack(len(header)), header] + [a.tobytes() for _, a in arrays])
    return body + signer.sign(body)


def decode_weights(data, verifier: Verifier, source: str = "weights message") -> dict:
    """A signed message back as a validated checkpoint; raises ``WeightsRefused``."""
    view = memoryview(data).cast("B")
    n = len(view)
    if n > MAX_MESSAGE_BYTES:
        raise _refused("bad weights", f"{source}: {n} bytes, more than a weights message may hold "
                       f"({MAX_MESSAGE_BYTES})")
    if n < len(MAGIC) + _HEAD.size + SIGNATURE_BYTES or bytes(view[:len(MAGIC)]) != MAGIC:
        raise _refused("unsigned weights", f"{source}: not a signed pusher-rl weights message")
    body, signature = view[:n - SIGNATURE_BYTES], view[n - SIGNATURE_BYTES:]
    if not verifier.verify(body, signature):
        raise _refused("unsigned weights", f"{source}: the signature is not this session's learner's")
    header, payload = _split(body, source)
    fields, shapes = _check_header(header, verifier.session, source)
    if "task" in header:  # validated with the checkpoint (checkpoint._check_task)
        fields = {**fields, "task": header["task"]}
    return _checkpoint(fields, shapes, payload, source)


def _refused(reason: str, detail: str) -> WeightsRefused:
    return WeightsRefused(Rejection(reason, detail))


def _split(body: memoryview, source: str) -> tuple[dict, memoryview]:
    start = len(MAGIC) + _HEAD.size
    (length,) = _HEAD.unpack(body[len(MAGIC):start])
    if length > MAX_HEADER_BYTES or start + length > len(body):
        raise _refused("bad weights", f"{source}: header of {length} bytes does not fit the message")
    try:
        header = json.loads(bytes(body[start:start + length]).decode("utf-8"))
    except (ValueError, UnicodeDecodeError, RecursionError):
        raise _refused("bad weights", f"{source}: the header is not JSON") from None
    if not isinstance(header, dict):
        raise _refused("bad weights", f"{source}: the header is not a JSON object")
    return header, body[start + length:]


def _check_header(header: dict, session: str, source: str) -> tuple[dict, list[tuple[str, tuple[int, ...]]]]:
    if header.get("format") != WEIGHTS_FORMAT or header.get("dtype") != DTYPE:
        raise _refused("bad weights", f"{source}: not a {WEIGHTS_FORMAT} message of {DTYPE} tensors")
    if header.get("session") != session:
        raise _refused("unsigned weights", f"{source}: signed for another session")
    fields = header.get("fields")
    if not isinstance(fields, dict) or set(fields) - set(SCALAR_FIELDS):
        raise _refused("bad weights", f"{source}: header fields must be among {', '.join(SCALAR_FIELDS)}")
    for name in REQUIRED_FIELDS:
        if name not in fields:
            raise _refused("bad weights", f"{source}: no '{name}' (unversioned weights are refused)"
                           if name == "weights_version" else f"{source}: no '{name}'")
    for name, value in fields.items():
        kind = SCALAR_FIELDS[name]
        top = MAX_WEIGHTS_VERSION if name == "weights_version" else MAX_COUNT
        ok = (isinstance(value, str) and len(value) <= 64 if kind is str else
              isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
              if kind is float else type(value) is int and 0 <= value <= top)
        if not ok:
            raise _refused("bad weights", f"{source}: field '{name}' is {str(value)[:40]!r}, expected "
                           + ("a short string" if kind is str else "a finite number" if kind is float
                              else f"an integer in [0, {top}]"))
    for name in ("obs_dim", "act_dim", "hidden"):
        if not 1 <= fields[name] <= MAX_WIDTH:
            raise _refused("bad weights", f"{source}: {name} {fields[name]} outside [1, {MAX_WIDTH}]")
    expected = expected_tensors(fields["obs_dim"], fields["act_dim"], fields["hidden"])
    listed = header.get("tensors")
    if not isinstance(listed, list) or not all(isinstance(t, list) and len(t) == 2 for t in listed):
        raise _refused("bad weights", f"{source}: 'tensors' must list [name, shape] pairs")
    shapes = []
    for name, shape in listed:
        if name not in expected or any(name == seen for seen, _ in shapes):
            raise _refused("bad weights", f"{source}: unexpected or repeated tensor {str(name)[:40]!r}")
        if not isinstance(shape, list) or tuple(shape) != expected[name]:
            raise _refused("bad weights", f"{source}: tensor '{name}' has shape {str(shape)[:40]}, "
                           f"expected {list(expected[name])}")
        shapes.append((name, expected[name]))
    missing = [name for name in expected if name not in OPTIONAL_TENSORS and name not in dict(shapes)]
    if missing:
        raise _refused("bad weights", f"{source}: missing tensor(s) {', '.join(missing)}")
    return fields, shapes


def _checkpoint(fields: dict, shapes: list[tuple[str, tuple[int, ...]]], payload: memoryview, source: str) -> dict:
    itemsize = np.dtype(DTYPE).itemsize
    sizes = [math.prod(shape) * itemsize for _, shape in shapes]
    if sum(sizes) > MAX_PAYLOAD_BYTES or sum(sizes) != len(payload):
        raise _refused("bad weights", f"{source}: the tensors need {sum(sizes)} bytes, the message holds "
                       f"{len(payload)}")
    ckpt: dict = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, **fields, "policy_state": {}}
    offset = 0
    for (name, shape), size in zip(shapes, sizes):
        values = np.frombuffer(payload, DTYPE, count=size // itemsize, offset=offset).reshape(shape)
        tensor = torch.from_numpy(values.astype(np.float32))  # a native copy: the message's buffer can go
        offset += size
        if name.startswith("policy_state."):
            ckpt["policy_state"][name.removeprefix("policy_state.")] = tensor
        else:
            ckpt[name] = tensor
    try:
        return validated_checkpoint(ckpt, source)
    except UserError as exc:
        raise _refused("bad weights", str(exc)) from None


def policy_from_weights_message(label: str, data, verifier: Verifier, source: str,
                                task: TaskSpec | str = DEFAULT_TASK) -> tuple[LoadedPolicy | None, Rejection | None]:
    """The policy a weights message carries (its layout label and bytes), or (None, why not):
    weights of another task than ``task`` (the acting node's) are refused."""
    if label != WEIGHTS_LABEL:
        return None, Rejection("bad layout", f"layout label {label[:40]!r}, expected {WEIGHTS_LABEL!r}")
    try:
        return policy_for_task(decode_weights(data, verifier, source), source, task), None
    except WeightsRefused as exc:
        return None, exc.rejection
    except UserError as exc:
        return None, Rejection("bad weights", str(exc))
    except Exception as exc:  # noqa: BLE001 - whatever a signed message still got wrong; keep serving
        return None, Rejection("bad weights", f"{source}: {type(exc).__name__}: {str(exc)[:120]}")
