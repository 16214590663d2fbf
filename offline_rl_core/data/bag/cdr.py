"""`/pusher/transition` messages as raw CDR, encoded and decoded with numpy.

A transition is a ``std_msgs/msg/Float32MultiArray`` whose ``layout.dim`` labels its
floats (``transitions.Layout``: obs, action, reward, next_obs, ... sized for the task; 25 on
pusher-reach). Every message of a topic written by one tool carries the same layout, so its
CDR bytes are one constant header followed by the floats. Decoding parses the header once
per distinct header, checks every payload carries exactly those bytes, then reads all
floats with a single ``np.frombuffer``: no Python object per message. One decode takes one
layout: a topic whose messages disagree on it is refused.

Stride convention: each field is a flat run of values, so ``stride`` = ``size`` for every
dimension. Readers check labels and sizes and ignore strides, since other tools may write
ROS' cumulative-product convention instead.
"""

from __future__ import annotations

import functools
import operator
import struct
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..transitions import PUSHER_LAYOUT, Layout

TRANSITION_TOPIC = "/pusher/transition"
TRANSITION_MSGTYPE = "std_msgs/msg/Float32MultiArray"

# CDR encapsulation ids (first two bytes, big-endian) of plain XCDR1.
_CDR_BE = 0x0000
_CDR_LE = 0x0001

# Payload bytes joined per step: under glibc's mmap threshold, so the buffer is reused.
_CHUNK_BYTES = 8 << 20


class TransitionDecodeError(ValueError):
    """A payload is not a Float32MultiArray with the transition layout."""


EXPECTED_LABELS = "obs, action, reward, next_obs, terminated, truncated, success, episode, step, source"


def transition_layout_msg_fields(layout: Layout = PUSHER_LAYOUT) -> dict:
    """The layout of a transition message, as plain fields for rclpy or rosbags.

    ``{"dim": [{"label": "obs", "size": 8, "stride": 8}, ...], "data_offset": 0}``; e.g.
    ``MultiArrayLayout(dim=[MultiArrayDimension(**d) for d in f["dim"]], data_offset=0)``.
    """
    return {
        "dim": [{"label": label, "size": size, "stride": size} for label, size in layout.fields],
        "data_offset": 0,
    }


@functools.lru_cache(maxsize=None)
def cdr_header(layout: Layout = PUSHER_LAYOUT, little_endian: bool = True) -> bytes:
    """Encapsulation + layout + data length: the bytes before the floats of every message."""
    end = "<" if little_endian else ">"
    out = bytearray(b"\x00\x01\x00\x00" if little_endian else b"\x00\x00\x00\x00")

    def u32(value: int) -> None:
        out.extend(struct.pack(end + "I", value))

    u32(len(layout.fields))
    for label, size in layout.fields:
        text = label.encode() + b"\x00"
        u32(len(text))
        out.extend(text)
        out.extend(b"\x00" * (-(len(out) - 4) % 4))  # CDR aligns after the 4-byte header
        u32(size)
        u32(size)  # stride
    u32(0)  # data_offset
    u32(layout.width)
    return bytes(out)


def message_size(layout: Layout = PUSHER_LAYOUT) -> int:
    return len(cdr_header(layout)) + 4 * layout.width


TRANSITION_CDR_HEADER = cdr_header()  # pusher-reach's
TRANSITION_MESSAGE_SIZE = message_size()


def encode_transition_rows(rows: np.ndarray, layout: Layout = PUSHER_LAYOUT) -> list[bytes]:
    """CDR bytes of one Float32MultiArray per row of an (N, width) float32 matrix."""
    rows = np.asarray(rows)
    if rows.ndim != 2 or rows.shape[1] != layout.width:
        raise ValueError(f"expected an (N, {layout.width}) matrix of transitions, got shape {rows.shape}")
    blob = encode_transition_blob(rows, layout)
    size = message_size(layout)
    return [blob[i : i + size] for i in range(0, len(blob), size)]


def encode_transition_blob(rows: np.ndarray, layout: Layout = PUSHER_LAYOUT) -> bytes:
    """All messages back to back (N * message_size(layout) bytes)."""
    rows = np.ascontiguousarray(rows, dtype="<f4")
    header = np.frombuffer(cdr_header(layout), np.uint8)
    out = np.empty((rows.shape[0], message_size(layout)), np.uint8)
    out[:, : header.size] = header
    out[:, header.size :] = rows.view(np.uint8).reshape(rows.shape[0], -1)
    return out.tobytes()


# header bytes -> (struct format, byte offsets of the terminated and truncated flags)
_DONE_FLAGS: dict[bytes, tuple[str, tuple[int, int]]] = {}


def transition_ends_episode(payload: bytes) -> bool:
    """Whether a transition message is its episode's last (terminated or truncated). Called
    per message by the recorder: a header seen before is not parsed again."""
    for prefix, (fmt, offsets) in _DONE_FLAGS.items():
        if payload.startswith(prefix) and len(payload) >= offsets[1] + 4:
            return any(struct.unpack_from(fmt, payload, at)[0] for at in offsets)
    known: list[_Header] = []
    header = _find_header(np.frombuffer(bytes(payload), np.uint8), known)
    slices = header.transition_layout.slices
    offsets = tuple(len(header.prefix) + 4 * slices[name].start for name in ("terminated", "truncated"))
    if len(_DONE_FLAGS) < 16:
        _DONE_FLAGS[header.prefix] = (header.float_dtype[0] + "f", offsets)
    return any(struct.unpack_from(header.float_dtype[0] + "f", payload, at)[0] for at in offsets)


@dataclass(frozen=True)
class _Header:
    prefix: bytes  # every byte before the first float of data (data_offset applied)
    layout: tuple[tuple[str, int], ...]
    float_dtype: str  # '<f4' or '>f4'
    width: int  # floats after the prefix that belong to the message (data length - data_offset)

    @property
    def transition_layout(self) -> Layout:
        return Layout.of_fields(self.layout)


def _parse_header(payload: bytes) -> _Header:
    """Parse a Float32MultiArray up to its float data; raises TransitionDecodeError."""
    if len(payload) < 4:
        raise TransitionDecodeError(f"a {len(payload)}-byte payload is too short for CDR")
    kind = int.from_bytes(payload[:2], "big")
    if kind not in (_CDR_LE, _CDR_BE):
        raise TransitionDecodeError(f"unsupported CDR encapsulation 0x{kind:04x} (expected plain CDR, 0x0000/0x0001)")
    end = "<" if kind == _CDR_LE else ">"
    pos = 4

    def u32() -> int:
        nonlocal pos
        pos += -(pos - 4) % 4
        if pos + 4 > len(payload):
            raise TransitionDecodeError(f"payload truncated at byte {pos} of {len(payload)}")
        (value,) = struct.unpack_from(end + "I", payload, pos)
        pos += 4
        return value

    ndim = u32()
    if ndim > 64:
        raise TransitionDecodeError(f"layout has {ndim} dimensions; not a transition message")
    layout = []
    for _ in range(ndim):
        n = u32()
        if n == 0 or pos + n > len(payload) or payload[pos + n - 1] != 0:  # CDR strings end in NUL
            raise TransitionDecodeError(f"bad label string of length {n} at byte {pos}")
        label = payload[pos : pos + n - 1].decode("utf-8", "replace")
        pos += n
        size = u32()
        u32()  # stride: ignored, conventions differ between tools
        layout.append((label, size))
    data_offset = u32()
    count = u32()
    start = pos + 4 * data_offset
    if count < data_offset or start + 4 * (count - data_offset) > len(payload):
        raise TransitionDecodeError(f"data of {count} floats (offset {data_offset}) runs past the {len(payload)}-byte payload")
    return _Header(bytes(payload[:start]), tuple(layout), end + "f4", count - data_offset)


def _check_layout(header: _Header) -> None:
    layout = Layout.of_fields(header.layout)
    if layout is None:
        got = ", ".join(f"{label or '<unlabelled>'} {size}" for label, size in header.layout) or "no dims"
        raise TransitionDecodeError(f"unknown layout [{got}]; expected the fields [{EXPECTED_LABELS}], "
                                    f"e.g. [{PUSHER_LAYOUT.describe()}]")
    if header.width != layout.width:
        raise TransitionDecodeError(f"data holds {header.width} floats; the layout [{layout.describe()}] needs "
                                    f"{layout.width}")


def _find_header(row: np.ndarray, known: list[_Header]) -> _Header:
    """The header of one payload row: a known one if its bytes match, else parsed and checked."""
    for header in known:
        p = len(header.prefix)
        # the same header bytes on a payload too short for its data is no match: parsed, refused
        if p + 4 * header.width <= row.size and row[:p].tobytes() == header.prefix:
            return header
    header = _parse_header(row.tobytes())
    _check_layout(header)
    if known and header.transition_layout != known[0].transition_layout:
        raise TransitionDecodeError(f"messages of two layouts: [{known[0].transition_layout.describe()}] and "
                                    f"[{header.transition_layout.describe()}]")
    known.append(header)
    return header


def _decode_block(mat: np.ndarray, out: np.ndarray, known: list[_Header]) -> None:
    """Decode an (m, L) uint8 matrix of equal-length payloads into ``out`` (m, width)."""
    m, length = mat.shape
    width = out.shape[1]
    # Compare headers as 32-bit words where the rows allow it: 4x fewer element compares.
    words = mat.view(np.uint32) if length % 4 == 0 else None
    pending: np.ndarray | None = None  # None: every row still pending (plain slices, no copies)
    while pending is None or pending.size:
        first = 0 if pending is None else int(pending[0])
        header = _find_header(mat[first], known)
        p = len(header.prefix)
        if words is not None and p % 4 == 0:
            cells, ref = words, np.frombuffer(header.prefix, np.uint32)
        else:
            cells, ref = mat, np.frombuffer(header.prefix, np.uint8)
        part = cells[:, : ref.size] if pending is None else cells[pending, : ref.size]
        match = (part == ref).all(axis=1)
        rows = np.flatnonzero(match) if pending is None else pending[match]
        if pending is None and rows.size == m:
            floats = mat[:, p : p + 4 * width]
            out[:] = np.ascontiguousarray(floats).view(header.float_dtype)
            return
        out[rows] = np.ascontiguousarray(mat[rows, p : p + 4 * width]).view(header.float_dtype)
        pending = (np.arange(m) if pending is None else pending)[~match]


def decode_transitions(payloads: Sequence[bytes]) -> tuple[np.ndarray, Layout]:
    """The (N, width) float32 rows of N raw CDR Float32MultiArray payloads, in order, and
    their layout (the one every payload must carry).

    Payloads may come from different writers (other label padding, endianness, data_offset):
    they are grouped by length and header bytes, each group decoded in one numpy pass per
    chunk of rows (chunks bound the temporary memory and keep it cache- and page-warm).
    Raises TransitionDecodeError for a payload that is not a transition, or of another layout.
    """
    n = len(payloads)
    if n == 0:
        return np.empty((0, PUSHER_LAYOUT.width), np.float32), PUSHER_LAYOUT
    known: list[_Header] = []
    first = _find_header(np.frombuffer(bytes(payloads[0]), np.uint8), known)
    layout = first.transition_layout
    out = np.empty((n, layout.width), np.float32)
    lengths = np.fromiter(map(len, payloads), np.int64, n)
    sizes = np.unique(lengths)
    for size in sizes:
        size = int(size)
        idx = None if sizes.size == 1 else np.flatnonzero(lengths == size)
        count = n if idx is None else idx.size
        step = max(1, _CHUNK_BYTES // max(size, 1))
        for lo in range(0, count, step):
            hi = min(lo + step, count)
            if idx is None:
                group, target = payloads[lo:hi], slice(lo, hi)
            else:
                target = idx[lo:hi]
                group = operator.itemgetter(*target)(payloads) if target.size > 1 else (payloads[int(target[0])],)
            mat = np.frombuffer(b"".join(group), np.uint8).reshape(hi - lo, size)
            if idx is None:
                _decode_block(mat, out[target], known)
            else:
                block = np.empty((hi - lo, layout.width), np.float32)
                _decode_block(mat, block, known)
                out[target] = block
    return out, layout


def decode_transition_payloads(payloads: Sequence[bytes], layout: Layout | None = None) -> np.ndarray:
    """``decode_transitions``' rows alone; with ``layout``, payloads of another layout are refused."""
    rows, found = decode_transitions(payloads)
    if layout is not None and len(payloads) and found != layout:
        raise TransitionDecodeError(f"layout [{found.describe()}]; expected [{layout.describe()}]")
    return rows
