"""Deterministic bad input for the nodes' fuzz tests (a seeded numpy generator, so a
failure reproduces from its seed).

Each generated case carries one defect (or none) and the rejection reason a node must
count for it (``offline_rl_core.common.rejections.REASONS``), or None where the node must take
the message. The reasons are written out here, case by case, from what the message is,
not computed with the code under test. Fields are plain Python values; the tests build
the ROS messages (``tests/test_ros_fuzz.py``) or call the plain checks directly
(``tests/test_bad_input.py``).
"""

from __future__ import annotations

import io
import math
import zipfile
from dataclasses import dataclass, field

import numpy as np
import torch

from offline_rl_core.data.transitions import LAYOUT_SLICES, TRANSITION_LAYOUT

JOINTS = ["shoulder", "elbow"]
NS = 1_000_000_000
HUGE = 1e38  # finite, and near float32's largest: the kind of value an uninitialised buffer holds


@dataclass
class Case:
    kind: str
    expect: str | None  # the reason the node must count, or None: taken
    fields: dict = field(default_factory=dict)


def _pick(rng: np.random.Generator, options):
    return options[int(rng.integers(len(options)))]


def _wild(rng: np.random.Generator) -> float:
    return _pick(rng, [math.nan, math.inf, -math.inf])


# ------------------------------------------------------------------ joint states and commands
JOINT_KINDS = ("valid", "reordered", "unnamed", "extra joint", "nan", "huge", "empty", "short", "long",
               "names and values differ", "unknown names", "duplicate names", "bad stamp")


def joint_case(rng: np.random.Generator, kind: str, values: tuple[str, ...], scale: float) -> Case:
    """A JointState whose ``values`` fields (("position", "velocity") for a state,
    ("effort",) for a command) carry ``kind`` of damage. Returns fields ``name``, the value
    fields, and ``bad_stamp`` (True: the test sends a stamp that is no valid time).

    ``expect`` is the reason for a *state*; commands differ in two cases the caller
    adjusts: an effort of 1e38 is clipped (taken), an empty effort is a teleop yield.
    """
    arrays = {f: [float(v) for v in rng.uniform(-scale, scale, 2)] for f in values}
    names, expect, bad_stamp = list(JOINTS), None, False
    if kind == "reordered":
        names = JOINTS[::-1]
        arrays = {f: v[::-1] for f, v in arrays.items()}
    elif kind == "unnamed":
        names = []
    elif kind == "extra joint":  # a bigger robot's JointState: the arm's two are picked out
        names = ["wrist", *JOINTS] if len(values) == 2 else names
        arrays = {f: [0.25, *v] if len(values) == 2 else v for f, v in arrays.items()}
    elif kind in ("nan", "huge"):
        f = _pick(rng, values)
        arrays[f][int(rng.integers(2))] = _wild(rng) if kind == "nan" else _pick(rng, [HUGE, -HUGE])
        expect = "non-finite" if kind == "nan" else "out of range"
    elif kind == "empty":
        names, arrays, expect = [], {f: [] for f in values}, "wrong length"
    elif kind == "short":
        names, expect = [], "wrong length"
        arrays = {f: v[:1] for f, v in arrays.items()}
    elif kind == "long":
        names, expect = [], "wrong length"
        arrays = {f: [*v, 0.5] for f, v in arrays.items()}
    elif kind == "names and values differ":
        names, expect = [*JOINTS, "wrist"], "wrong length"
    elif kind == "unknown names":
        names, expect = _pick(rng, [["wrist", "elbow"], ["a", "b"], ["shoulder", "x" * 300]]), "unknown joints"
    elif kind == "duplicate names":
        names, expect = _pick(rng, [["elbow", "elbow"], ["shoulder", "shoulder"]]), "duplicate joints"
    elif kind == "bad stamp":
        bad_stamp, expect = True, "bad stamp"
    elif kind != "valid":
        raise ValueError(kind)
    return Case(kind, expect, {"name": names, **arrays, "bad_stamp": bad_stamp})


def command_case(rng: np.random.Generator, kind: str, allow_empty: bool = False) -> Case:
    """A command (effort = action, clipped to [-1, 1]); see :func:`joint_case`."""
    case = joint_case(rng, kind, ("effort",), 1.5)
    if kind == "huge":
        case.expect = None  # an effort of 1e38 is clipped to the action range: taken
    if kind == "empty" and allow_empty:
        case.expect = None  # a teleop yield
    return case


def bad_stamp(rng: np.random.Generator) -> tuple[int, int]:
    """(sec, nanosec) that is no valid time."""
    return _pick(rng, [(int(rng.integers(1, 2**31 - 1)), int(rng.integers(NS, 2**32))),
                       (-int(rng.integers(1, 2**31)), 0)])


# ------------------------------------------------------------------ points (target, fingertip)
POINT_KINDS = ("valid", "nan", "huge", "bad stamp")


def point_case(rng: np.random.Generator, kind: str) -> Case:
    xy = [float(v) for v in rng.uniform(-0.2, 0.2, 2)]
    expect, stamp_bad = None, False
    if kind == "nan":
        xy[int(rng.integers(2))], expect = _wild(rng), "non-finite"
    elif kind == "huge":
        xy[int(rng.integers(2))], expect = _pick(rng, [HUGE, -HUGE, 1e5]), "out of range"
    elif kind == "bad stamp":
        stamp_bad, expect = True, "bad stamp"
    return Case(kind, expect, {"xy": xy, "bad_stamp": stamp_bad})


# ------------------------------------------------------------------ transitions (the learner)
TRANSITION_KINDS = ("valid", "nan", "huge action", "huge value", "flag", "count", "source", "empty", "wrong length",
                    "wrong labels", "reordered labels", "garbage bytes", "truncated bytes")


def transition_case(rng: np.random.Generator, kind: str, rows: np.ndarray) -> Case:
    """A pusher/transition: fields ``data`` and ``layout`` ((label, size) pairs), or
    ``raw`` (serialized bytes published as they are)."""
    row = rows[int(rng.integers(len(rows)))].astype(np.float64).copy()
    layout, expect = list(TRANSITION_LAYOUT), None
    if kind == "nan":
        row[int(rng.integers(len(row)))], expect = _wild(rng), "non-finite"
    elif kind == "huge action":
        row[LAYOUT_SLICES["action"].start + int(rng.integers(2))] = _pick(rng, [HUGE, -1.5, 3.0])
        expect = "out of range"
    elif kind == "huge value":
        label = _pick(rng, ["obs", "reward", "next_obs"])
        sl = LAYOUT_SLICES[label]
        row[sl.start + int(rng.integers(sl.stop - sl.start))], expect = _pick(rng, [HUGE, -HUGE, 1e6]), "out of range"
    elif kind == "flag":
        row[LAYOUT_SLICES[_pick(rng, ["terminated", "truncated", "success"])].start] = _pick(rng, [0.5, 2.0, -1.0])
        expect = "out of range"
    elif kind == "count":
        row[LAYOUT_SLICES[_pick(rng, ["episode", "step"])].start] = _pick(rng, [-1.0, 2.5, 1e9])
        expect = "out of range"
    elif kind == "source":
        row[LAYOUT_SLICES["source"].start], expect = _pick(rng, [4.0, -1.0, 2.5, 99.0]), "unknown source"
    elif kind == "empty":
        return Case(kind, "bad layout", {"data": [], "layout": []})
    elif kind == "wrong length":
        n = _pick(rng, [1, 24, 26, 100])
        data = [float(v) for v in rng.uniform(-1, 1, n)]
        return Case(kind, "bad layout", {"data": data, "layout": _pick(rng, [layout, [("data", n)]])})
    elif kind == "wrong labels":
        layout[int(rng.integers(len(layout)))] = ("nonsense", layout[0][1])
        expect = "bad layout"
    elif kind == "reordered labels":
        i = int(rng.integers(len(layout) - 1))
        layout[i], layout[i + 1] = layout[i + 1], layout[i]
        expect = "bad layout"
    elif kind == "garbage bytes":
        return Case(kind, "bad layout", {"raw": rng.bytes(int(rng.integers(4, 400)))})
    elif kind == "truncated bytes":
        return Case(kind, "bad layout", {"truncate": int(rng.integers(4, 300)), "data": [float(v) for v in row],
                                         "layout": layout})
    elif kind != "valid":
        raise ValueError(kind)
    return Case(kind, expect, {"data": [float(v) for v in row], "layout": layout})


# ------------------------------------------------------------------ weights messages (the policy node)
WEIGHTS_KINDS = ("random bytes", "empty", "truncated", "bit flip", "wrong label", "no layout", "wrong dims",
                 "non-finite weights", "unversioned", "another key", "pickle checkpoint", "stride-0 pickle",
                 "version far ahead")


def checkpoint_bytes(checkpoint: dict) -> bytes:
    buf = io.BytesIO()
    torch.save(checkpoint, buf)
    return buf.getvalue()


def broken_checkpoints(good: dict) -> dict[str, bytes]:
    """Well-formed torch files that are no policy for this task (checkpoint files; made once per test)."""
    wrong_dims = {**good, "obs_dim": 5, "policy_state": {**good["policy_state"]}}
    wrong_dims["policy_state"]["0.weight"] = torch.zeros(int(good["hidden"]), 5)
    nan = {**good, "policy_state": {**good["policy_state"]}}
    nan["policy_state"]["4.bias"] = torch.full_like(good["policy_state"]["4.bias"], float("nan"))
    return {"wrong dims": checkpoint_bytes(wrong_dims), "non-finite weights": checkpoint_bytes(nan),
            "not a checkpoint": checkpoint_bytes({"format": "something else", "weights": torch.ones(3)})}


def flip_in_tensor_data(data: bytes) -> bytes:
    """``data`` (a torch.save zip) with one bit flipped inside its largest tensor record:
    torch.load reads it as other weights; only the zip's CRC tells."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        info = max((i for i in archive.infolist() if "/data/" in i.filename), key=lambda i: i.file_size)
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)  # past the local header
    flipped = bytearray(data)
    flipped[start + info.file_size // 2] ^= 0x10
    return bytes(flipped)


def stride0_checkpoint(hidden: int = 8192) -> bytes:
    """The review's 2 KB message: a torch file whose (hidden, hidden) layer is one float
    broadcast (stride 0), hundreds of MiB once materialised."""
    layer = torch.zeros(1).expand(hidden, hidden)
    state = {"0.weight": torch.zeros(1).expand(hidden, 8), "0.bias": torch.zeros(1).expand(hidden),
             "2.weight": layer, "2.bias": torch.zeros(1).expand(hidden),
             "4.weight": torch.zeros(1).expand(2, hidden), "4.bias": torch.zeros(2)}
    return checkpoint_bytes({"format": "pusher-rl/policy", "version": 1, "algorithm": "sac", "obs_dim": 8,
                             "act_dim": 2, "hidden": hidden, "policy_state": state, "weights_version": 2**62})


def broken_weights(good: dict, signer, version: int = 1) -> dict[str, bytes]:
    """Messages that are no weights this node may act on (made once per test). ``good`` is a
    checkpoint; ``signer`` the session's key: the signed ones get past the signature."""
    from offline_rl_core.serving.signing import Signer
    from offline_rl_core.serving.weights import encode_weights

    good = {**good, "weights_version": version}
    wrong_dims = {**good, "obs_dim": 5, "policy_state": {**good["policy_state"]}}
    wrong_dims["policy_state"]["0.weight"] = torch.zeros(int(good["hidden"]), 5)
    nan = {**good, "policy_state": {**good["policy_state"]}}
    nan["policy_state"]["4.bias"] = torch.full_like(good["policy_state"]["4.bias"], float("nan"))
    unversioned = {k: v for k, v in good.items() if k != "weights_version"}
    # the project's own encoder, a key of its own: version 2**62 and a saturating bias
    rogue = {**good, "weights_version": 2**62, "policy_state": {**good["policy_state"]}}
    rogue["policy_state"]["4.bias"] = torch.full_like(good["policy_state"]["4.bias"], 1e6)
    return {"wrong dims": encode_weights(wrong_dims, signer), "non-finite weights": encode_weights(nan, signer),
            "unversioned": encode_weights(unversioned, signer), "another key": encode_weights(rogue, Signer.generate()),
            "pickle checkpoint": checkpoint_bytes(good), "stride-0 pickle": stride0_checkpoint(),
            "version far ahead": encode_weights({**good, "weights_version": 2**62}, signer)}


WEIGHTS_EXPECT = {"wrong dims": "bad weights", "non-finite weights": "bad weights", "unversioned": "bad weights",
                  "another key": "unsigned weights", "pickle checkpoint": "unsigned weights",
                  "stride-0 pickle": "unsigned weights", "version far ahead": "bad weights"}


def weights_case(rng: np.random.Generator, kind: str, good: bytes, broken: dict[str, bytes]) -> Case:
    """A learner/weights message: fields ``label`` (None: no layout dim) and ``data``.
    ``good`` is a signed message; every change to it breaks its signature."""
    label, expect = "pusher-rl/weights", "unsigned weights"
    if kind == "random bytes":
        data = rng.bytes(int(rng.integers(1, 3000)))
    elif kind == "empty":
        data = b""
    elif kind == "truncated":
        data = good[:int(rng.integers(1, len(good)))]
    elif kind == "bit flip":
        flipped = bytearray(good)
        for _ in range(int(rng.integers(1, 4))):
            flipped[int(rng.integers(len(flipped)))] ^= 1 << int(rng.integers(8))
        data = bytes(flipped)
        if bytes(flipped) == good:  # flips that undid each other
            data, expect = good, None
    elif kind == "wrong label":
        data, label, expect = good, _pick(rng, ["", "weights", "pusher-rl/weights2"]), "bad layout"
    elif kind == "no layout":
        data, label, expect = good, None, "bad layout"
    else:
        data, expect = broken[kind], WEIGHTS_EXPECT[kind]
    return Case(kind, expect, {"label": label, "data": data})
