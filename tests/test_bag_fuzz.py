"""Property-based tests: the vectorised CDR decoder against rosbags' own deserializer, and
the bag reader on truncated and bit-flipped files.

The decoder must return exactly what rosbags' ``deserialize_cdr`` reads for every
message whose layout is the transition layout, and a TransitionDecodeError for every
other byte string, never another exception. The reader must return the rows that were
written, or one UserError line naming the file: never a traceback, never other rows.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from offline_rl_core.data.bag import (
    TRANSITION_MSGTYPE, TRANSITION_TOPIC, BagWriter, TransitionDecodeError, decode_transition_payloads,
    encode_transition_rows, read_transitions, typestore,
)
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.common.errors import UserError
from offline_rl_core.data.transitions import TRANSITION_LAYOUT, TRANSITION_WIDTH

FAST = settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
TS = typestore()
Msg, Layout, Dim = (TS.types[f"std_msgs/msg/{n}"] for n in ("Float32MultiArray", "MultiArrayLayout", "MultiArrayDimension"))
floats32 = st.floats(width=32, allow_nan=True, allow_infinity=True)


@st.composite
def layouts(draw):
    """Mostly the transition layout (so the decoding path runs), else a near miss."""
    dims = [list(d) for d in TRANSITION_LAYOUT]
    change = draw(st.sampled_from(["none", "none", "none", "label", "size", "drop", "extra", "swap", "random"]))
    if change == "label":
        dims[draw(st.integers(0, len(dims) - 1))][0] = draw(st.text(max_size=12))
    elif change == "size":
        dims[draw(st.integers(0, len(dims) - 1))][1] = draw(st.integers(0, 40))
    elif change == "drop":
        del dims[draw(st.integers(0, len(dims) - 1))]
    elif change == "extra":
        dims.insert(draw(st.integers(0, len(dims))), [draw(st.text(max_size=8)), draw(st.integers(0, 5))])
    elif change == "swap":
        i, j = draw(st.integers(0, len(dims) - 1)), draw(st.integers(0, len(dims) - 1))
        dims[i], dims[j] = dims[j], dims[i]
    elif change == "random":
        dims = draw(st.lists(st.tuples(st.text(max_size=10), st.integers(0, 30)).map(list), max_size=12))
    strides = [draw(st.sampled_from([size, 0, 25, size * 3])) for _, size in dims]
    return [Dim(label=label, size=size, stride=stride) for (label, size), stride in zip(dims, strides)]


@st.composite
def messages(draw):
    dims = draw(layouts())
    offset = draw(st.sampled_from([0, 0, 0, 1, 3]))
    width = sum(d.size for d in dims)
    n = offset + width + draw(st.sampled_from([0, 0, 0, 0, -1, 1, 7]))
    data = draw(arrays(np.float32, max(n, 0), elements=floats32))
    msg = Msg(layout=Layout(dim=dims, data_offset=offset), data=data)
    return bytes(TS.serialize_cdr(msg, TRANSITION_MSGTYPE, little_endian=draw(st.booleans())))


def rosbags_rows(payload: bytes) -> np.ndarray | None:
    """What rosbags reads from a payload, as a transition row; None if not a transition."""
    try:
        msg = TS.deserialize_cdr(payload, TRANSITION_MSGTYPE)
    except Exception:
        return None
    layout = tuple((d.label, int(d.size)) for d in msg.layout.dim)
    data = np.asarray(msg.data)[int(msg.layout.data_offset) :]
    if layout != TRANSITION_LAYOUT or len(data) != TRANSITION_WIDTH:
        return None
    return data.astype(np.float32)


def same_floats(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal bit for bit, except that any NaN equals any NaN."""
    nan_a, nan_b = np.isnan(a), np.isnan(b)
    return bool((nan_a == nan_b).all() and (a.view(np.uint32)[~nan_a] == b.view(np.uint32)[~nan_b]).all())


def check_decoder(payloads: list[bytes]) -> None:
    expected = [rosbags_rows(p) for p in payloads]
    if all(e is not None for e in expected):
        got = decode_transition_payloads(payloads)
        assert got.shape == (len(payloads), TRANSITION_WIDTH)
        assert same_floats(got, np.stack(expected))
    else:
        with pytest.raises(TransitionDecodeError):
            decode_transition_payloads(payloads)


@FAST
@given(st.lists(messages(), min_size=1, max_size=6))
def test_decoder_agrees_with_rosbags_on_generated_messages(payloads):
    check_decoder(payloads)


@FAST
@given(st.lists(st.binary(max_size=300), min_size=1, max_size=3))
def test_decoder_refuses_garbage_with_its_own_error(payloads):
    check_decoder(payloads)


VALID = encode_transition_rows(np.random.default_rng(1).uniform(-2, 2, (4, TRANSITION_WIDTH)).astype(np.float32))


@FAST
@given(st.data())
def test_decoder_on_mutated_payloads(data):
    """Cut or flipped payloads among good ones: rosbags' reading, or the decoder's error."""
    payloads = list(VALID)
    i = data.draw(st.integers(0, len(payloads) - 1))
    raw = bytearray(payloads[i])
    if data.draw(st.booleans()):
        raw = raw[: data.draw(st.integers(0, len(raw) - 1))]
    else:
        for at in data.draw(st.lists(st.integers(0, len(raw) * 8 - 1), min_size=1, max_size=3)):
            raw[at // 8] ^= 1 << (at % 8)
    payloads[i] = bytes(raw)
    check_decoder(payloads)


# ------------------------------------------------------------------ the bag reader
ROWS = collect_transitions(2, 0.5, 5).to_rows()[:120]


def _recorded(name: str) -> bytes:
    """A bag as the recorder writes it (several flushes), as bytes."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / name
        with BagWriter(path, flush_interval=3600) as bag:
            bag.add_topic("/pusher/state", "sensor_msgs/msg/JointState")
            bag.add_topic(TRANSITION_TOPIC, TRANSITION_MSGTYPE)
            for i, payload in enumerate(encode_transition_rows(ROWS)):
                bag.write(TRANSITION_TOPIC, 10**9 + i * 20_000_000, payload)
                if i % 40 == 39:
                    bag.flush()
        return path.read_bytes()


BAGS = {name: _recorded(name) for name in ("r.db3", "r.mcap")}
WORK = Path(tempfile.mkdtemp(prefix="bag_fuzz."))


def check_reader(name: str, data: bytes, tag: str) -> None:
    path = WORK / f"{tag}{name}"
    path.write_bytes(data)
    for sidecar in (Path(f"{path}-wal"), Path(f"{path}-shm")):
        sidecar.unlink(missing_ok=True)
    try:
        got = read_transitions(path).to_rows()
    except UserError as exc:
        message = str(exc)
        assert "\n" not in message and str(path) in message, message
        return
    finally:
        path.unlink()
    assert np.array_equal(got, ROWS), f"{path}: other rows than were written"


@FAST
@pytest.mark.parametrize("name", list(BAGS))
@given(cut=st.floats(0, 1, exclude_max=True))
def test_reader_on_truncated_bags(name, cut):
    data = BAGS[name]
    check_reader(name, data[: int(cut * len(data))], "cut")


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@pytest.mark.parametrize("name", list(BAGS))
@given(bits=st.lists(st.integers(0, 10**9), min_size=1, max_size=3))
def test_reader_on_bit_flipped_bags(name, bits):
    data = bytearray(BAGS[name])
    flips = sorted({b % (len(data) * 8) for b in bits})
    for at in flips:
        data[at // 8] ^= 1 << (at % 8)
    assume(bytes(data) != BAGS[name])
    check_reader(name, bytes(data), "flip")
