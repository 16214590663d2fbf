"""Decoding a topic's raw CDR messages with numpy: JointState, PointStamped, PoseStamped,
Float64MultiArray.

A robot's driver publishes the same joint names and frame id in every message, so all
messages of a topic share one byte layout and differ only in their stamps and numbers.
Decoding walks the first message of a group of equal-length payloads to find that layout
(where the stamp and each float64 array sit, and which bytes are the same in every message
of that layout: names, lengths, frame id, padding), checks the other payloads carry those
same bytes, and reads stamps and arrays of all matching rows with numpy views: no Python
object per message. Rows that do not match start a new layout; past ``MAX_LAYOUTS`` layouts
in a group (a driver writing a different frame id into every message, say) the rest are
walked one by one.

Plain CDR (XCDR1, little or big endian) as rosbag2 stores it. A payload the walk cannot
read raises MessageDecodeError naming the byte where it failed.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

JOINT_STATE = "sensor_msgs/msg/JointState"
POINT_STAMPED = "geometry_msgs/msg/PointStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
FLOAT64_MULTI_ARRAY = "std_msgs/msg/Float64MultiArray"
HAS_HEADER = {JOINT_STATE: True, POINT_STAMPED: True, POSE_STAMPED: True, FLOAT64_MULTI_ARRAY: False}

MAX_LAYOUTS = 32  # per group of equal-length payloads, before walking row by row
_CHUNK_BYTES = 8 << 20  # payload bytes stacked into one matrix at a time


class MessageDecodeError(ValueError):
    """A payload is not a readable CDR message of the expected type."""


@dataclass(frozen=True)
class Layout:
    """Where the parts of one message layout sit (byte offsets from the payload's start)."""

    little_endian: bool
    stamp: int | None  # builtin_interfaces/Time: int32 sec, uint32 nanosec
    frame_id: str
    names: tuple[str, ...]  # JointState.name, or the dim labels of a MultiArray
    arrays: tuple[tuple[str, int, int], ...]  # (field, byte offset, count) of float64 arrays
    data_offset: int = 0  # MultiArray layout.data_offset

    def variable_spans(self) -> list[tuple[int, int]]:
        """(start, stop) byte ranges that differ between messages of this layout."""
        spans = [(off, off + 8 * n) for _, off, n in self.arrays if n]
        if self.stamp is not None:
            spans.append((self.stamp, self.stamp + 8))
        return sorted(spans)


class _Walker:
    """Reads a CDR payload field by field, recording offsets rather than values."""

    def __init__(self, payload: bytes):
        if len(payload) < 4:
            raise MessageDecodeError(f"a {len(payload)}-byte payload is too short for CDR")
        kind = int.from_bytes(payload[:2], "big")
        if kind not in (0x0000, 0x0001):
            raise MessageDecodeError(f"unsupported CDR encapsulation 0x{kind:04x} (expected plain CDR)")
        self.payload = payload
        self.little = kind == 0x0001
        self.end = "<" if self.little else ">"
        self.pos = 4

    def _need(self, n: int) -> None:
        if self.pos + n > len(self.payload):
            raise MessageDecodeError(f"payload truncated at byte {self.pos} of {len(self.payload)}")

    def align(self, n: int) -> None:
        self.pos += -(self.pos - 4) % n

    def u32(self) -> int:
        self.align(4)
        self._need(4)
        (value,) = struct.unpack_from(self.end + "I", self.payload, self.pos)
        self.pos += 4
        return value

    def string(self) -> str:
        n = self.u32()
        if n == 0:
            raise MessageDecodeError(f"bad string length 0 at byte {self.pos - 4}")
        self._need(n)
        text = self.payload[self.pos : self.pos + n - 1].decode("utf-8", "replace")
        self.pos += n
        return text

    def stamp(self) -> int:
        self.align(4)
        self._need(8)
        at = self.pos
        self.pos += 8
        return at

    def f64_seq(self) -> tuple[int, int]:
        n = self.u32()
        if n:
            self.align(8)
            self._need(8 * n)
        at = self.pos
        self.pos += 8 * n
        return at, n

    def f64(self) -> int:
        self.align(8)
        self._need(8)
        at = self.pos
        self.pos += 8
        return at


def header_stamp_ns(payload: bytes, msgtype: str) -> int | None:
    """The header stamp (ns) of one message of a type that starts with a std_msgs/Header,
    without decoding the rest; None for a type without one or a payload too short to hold it."""
    if not HAS_HEADER.get(msgtype, False) or len(payload) < 12 or payload[0] != 0 or payload[1] not in (0, 1):
        return None
    sec, nanosec = struct.unpack_from("<iI" if payload[1] == 1 else ">iI", payload, 4)
    return sec * 1_000_000_000 + nanosec


def _walk_joint_state(w: _Walker) -> Layout:
    stamp = w.stamp()
    frame_id = w.string()
    names = tuple(w.string() for _ in range(w.u32()))
    arrays = tuple((key, *w.f64_seq()) for key in ("position", "velocity", "effort"))
    return Layout(w.little, stamp, frame_id, names, arrays)


def _walk_point_stamped(w: _Walker) -> Layout:
    stamp = w.stamp()
    frame_id = w.string()
    x = w.f64()
    w.f64(), w.f64()  # y, z follow x directly: 8-byte values stay aligned
    return Layout(w.little, stamp, frame_id, (), (("point", x, 3),))


def _walk_pose_stamped(w: _Walker) -> Layout:
    stamp = w.stamp()
    frame_id = w.string()
    x = w.f64()
    for _ in range(6):  # position y, z and the orientation quaternion follow, aligned
        w.f64()
    return Layout(w.little, stamp, frame_id, (), (("point", x, 3), ("orientation", x + 24, 4)))


def _walk_float64_multi_array(w: _Walker) -> Layout:
    labels = []
    for _ in range(w.u32()):
        labels.append(w.string())
        w.u32(), w.u32()  # size, stride
    data_offset = w.u32()
    return Layout(w.little, None, "", tuple(labels), (("data", *w.f64_seq()),), data_offset)


WALKERS: dict[str, Callable[[_Walker], Layout]] = {
    JOINT_STATE: _walk_joint_state,
    POINT_STAMPED: _walk_point_stamped,
    POSE_STAMPED: _walk_pose_stamped,
    FLOAT64_MULTI_ARRAY: _walk_float64_multi_array,
}


def walk(payload: bytes, msgtype: str) -> Layout:
    """The layout of one payload of ``msgtype``; MessageDecodeError if it cannot be read."""
    return WALKERS[msgtype](_Walker(payload))


@dataclass
class Decoded:
    """Rows of a topic that share one layout: their indices, stamps and float64 arrays."""

    layout: Layout
    rows: np.ndarray  # int64 indices into the topic's payloads
    stamp_ns: np.ndarray | None  # int64 header stamps, None for types without a header
    arrays: dict  # field -> float64 (k, count)


def decode_messages(payloads: Sequence[bytes], msgtype: str) -> list[Decoded]:
    """Every payload of a topic, decoded; one Decoded per layout (rows in payload order
    within each). Raises MessageDecodeError naming the first unreadable message."""
    n = len(payloads)
    if n == 0:
        return []
    walker = WALKERS[msgtype]
    if n == 1:  # one message as it arrives (the live join): its walk gives every offset
        return [_decode_one(bytes(payloads[0]), walker)]
    lengths = np.fromiter(map(len, payloads), np.int64, n)
    parts: dict[Layout, list[tuple[np.ndarray, np.ndarray]]] = {}  # layout -> [(rows, matrix)]
    for size in np.unique(lengths):
        idx = np.flatnonzero(lengths == size)
        step = max(1, _CHUNK_BYTES // int(size))
        for lo in range(0, idx.size, step):
            rows = idx[lo : lo + step]
            block = b"".join(payloads[int(i)] for i in rows)
            mat = np.frombuffer(block, np.uint8).reshape(rows.size, int(size))
            _split_by_layout(mat, rows, walker, parts)
    out = []
    for layout, chunks in parts.items():
        rows = np.concatenate([r for r, _ in chunks])
        order = np.argsort(rows, kind="stable")
        stamps, arrays = [], {key: [] for key, _, _ in layout.arrays}
        for r, mat in chunks:
            if layout.stamp is not None:
                stamps.append(_read_stamps(mat, layout))
            for key, off, count in layout.arrays:
                dtype = "<f8" if layout.little_endian else ">f8"
                arrays[key].append(np.ascontiguousarray(mat[:, off : off + 8 * count]).view(dtype).astype(np.float64))
        out.append(Decoded(
            layout,
            rows[order],
            np.concatenate(stamps)[order] if stamps else None,
            {key: np.concatenate(v)[order] for key, v in arrays.items()},
        ))
    return out


def _decode_one(payload: bytes, walker) -> Decoded:
    try:
        layout = walker(_Walker(payload))
    except MessageDecodeError as exc:
        raise MessageDecodeError(f"message 1: {exc}") from None
    end = "<" if layout.little_endian else ">"
    stamp = None
    if layout.stamp is not None:
        sec, nanosec = struct.unpack_from(end + "iI", payload, layout.stamp)
        stamp = np.array([sec * 1_000_000_000 + nanosec], np.int64)
    arrays = {key: np.frombuffer(payload, end + "f8", count, off).astype(np.float64).reshape(1, count)
              for key, off, count in layout.arrays}
    return Decoded(layout, np.zeros(1, np.int64), stamp, arrays)


def _read_stamps(mat: np.ndarray, layout: Layout) -> np.ndarray:
    end = "<" if layout.little_endian else ">"
    at = layout.stamp
    sec = np.ascontiguousarray(mat[:, at : at + 4]).view(end + "i4")[:, 0].astype(np.int64)
    nanosec = np.ascontiguousarray(mat[:, at + 4 : at + 8]).view(end + "u4")[:, 0].astype(np.int64)
    return sec * 1_000_000_000 + nanosec


def _split_by_layout(mat: np.ndarray, rows: np.ndarray, walker, parts: dict) -> None:
    """Group the rows of an (m, L) payload matrix by layout into ``parts``."""
    pending = np.arange(mat.shape[0])
    layouts = 0
    while pending.size:
        first = int(pending[0])
        if layouts >= MAX_LAYOUTS:  # one layout per message or so: walk the rest one by one
            for i in pending:
                layout = _walk_row(mat, rows, int(i), walker)
                parts.setdefault(layout, []).append((rows[i : i + 1], mat[i : i + 1]))
            return
        layout = _walk_row(mat, rows, first, walker)
        layouts += 1
        match = np.ones(pending.size, bool)
        start = 0
        for lo, hi in [*layout.variable_spans(), (mat.shape[1], mat.shape[1])]:
            if lo > start:  # the bytes between two variable spans are the layout's own
                block = mat[pending, start:lo] if pending.size < mat.shape[0] else mat[:, start:lo]
                match &= (block == mat[first, start:lo]).all(axis=1)
            start = max(start, hi)
        taken = pending[match]
        parts.setdefault(layout, []).append((rows[taken], mat[taken]))
        pending = pending[~match]


def _walk_row(mat: np.ndarray, rows: np.ndarray, i: int, walker) -> Layout:
    try:
        return walker(_Walker(mat[i].tobytes()))
    except MessageDecodeError as exc:
        raise MessageDecodeError(f"message {int(rows[i]) + 1}: {exc}") from None
