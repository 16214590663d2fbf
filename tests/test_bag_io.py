"""rosbag2 dataset I/O: round trips, bags from other writers, info, the streaming writer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from offline_rl_core.data.bag import (
    TRANSITION_MSGTYPE, TRANSITION_TOPIC, BagWriter, bag_info, decode_transition_payloads, encode_transition_rows,
    read_transitions, transition_layout_msg_fields, typestore, write_transitions,
)
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.data.transitions import TRANSITION_WIDTH

REPO = Path(__file__).resolve().parents[1]
FAKE_HASH = "RIHS01_" + "0" * 64


@pytest.fixture(scope="module")
def small():
    return collect_transitions(4, 0.5, 7)


def _rosbags_message(rows_row, stride=None):
    """A Float32MultiArray built and serialized by rosbags' typestore, not by our encoder."""
    ts = typestore()
    Msg = ts.types["std_msgs/msg/Float32MultiArray"]
    Layout = ts.types["std_msgs/msg/MultiArrayLayout"]
    Dim = ts.types["std_msgs/msg/MultiArrayDimension"]
    fields = transition_layout_msg_fields()
    dims = [Dim(label=d["label"], size=d["size"], stride=stride or d["stride"]) for d in fields["dim"]]
    return Msg(layout=Layout(dim=dims, data_offset=0), data=np.asarray(rows_row, np.float32))


def _same(a, b) -> bool:
    return np.array_equal(a.to_rows(), b.to_rows())


@pytest.mark.parametrize("name,storage", [("t.db3", None), ("t.mcap", None), ("dir_sqlite", None), ("dir_mcap", "mcap")])
def test_round_trip(tmp_path, small, name, storage):
    path = tmp_path / name
    write_transitions(path, small, storage=storage)
    assert _same(read_transitions(path), small)
    if path.is_dir():
        assert (path / "metadata.yaml").is_file()
        assert (path / f"{name}{'.mcap' if storage == 'mcap' else '.db3'}").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]  # no staging leftovers
    with Reader(path) as reader:  # rosbags itself reads it
        assert reader.message_count == len(small)
        assert reader.topics[TRANSITION_TOPIC].msgtype == TRANSITION_MSGTYPE


def test_single_db3_is_self_describing(tmp_path, small):
    import sqlite3

    path = tmp_path / "x.db3"
    write_transitions(path, small)
    con = sqlite3.connect(path)
    assert con.execute("SELECT schema_version FROM schema").fetchone()[0] >= 4
    (meta,) = con.execute("SELECT metadata FROM metadata").fetchone()
    con.close()
    assert "relative_file_paths" in meta and "x.db3" in meta


def test_encoder_matches_rosbags_serializer(small):
    rows = small.to_rows()
    ours = encode_transition_rows(rows[:3])
    ts = typestore()
    for row, payload in zip(rows[:3], ours):
        assert payload == bytes(ts.serialize_cdr(_rosbags_message(row), TRANSITION_MSGTYPE))
    assert np.array_equal(decode_transition_payloads(ours), rows[:3])


def test_decode_groups_mixed_headers(small):
    """Payloads from different writers (endianness, stride convention) in one topic."""
    rows = small.to_rows()[:6]
    ts = typestore()
    big_endian = bytes(ts.serialize_cdr(_rosbags_message(rows[1]), TRANSITION_MSGTYPE, little_endian=False))
    other_stride = bytes(ts.serialize_cdr(_rosbags_message(rows[3], stride=25), TRANSITION_MSGTYPE))
    ours = encode_transition_rows(rows)
    mixed = [ours[0], big_endian, ours[2], other_stride, ours[4], ours[5]]
    assert np.array_equal(decode_transition_payloads(mixed), rows)
    assert decode_transition_payloads([]).shape == (0, TRANSITION_WIDTH)


@pytest.mark.parametrize("plugin", [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_bag_from_rosbags_writer_with_extra_topics(tmp_path, small, plugin):
    """A bag written by rosbags' own Writer with typestore serialization, plus other topics."""
    ts = typestore()
    rows = small.to_rows()
    path = tmp_path / "foreign"
    with Writer(path, version=8, storage_plugin=plugin) as writer:
        state = writer.add_connection("/pusher/state", "sensor_msgs/msg/JointState", typestore=ts)
        gizmo = writer.add_connection("/gizmo", "acme_msgs/msg/Gizmo", msgdef="int32 x", rihs01=FAKE_HASH)
        trans = writer.add_connection(TRANSITION_TOPIC, TRANSITION_MSGTYPE, typestore=ts)
        joint = ts.types["sensor_msgs/msg/JointState"]
        header = ts.types["std_msgs/msg/Header"](stamp=ts.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="")
        empty = np.zeros(2)
        for i, row in enumerate(rows):
            stamp = 1_000 + i * 10
            msg = joint(header=header, name=["shoulder", "elbow"], position=empty, velocity=empty, effort=empty)
            writer.write(state, stamp, ts.serialize_cdr(msg, "sensor_msgs/msg/JointState"))
            writer.write(gizmo, stamp + 1, b"\x00\x01\x00\x00\x05\x00\x00\x00")
            writer.write(trans, stamp + 2, ts.serialize_cdr(_rosbags_message(row), TRANSITION_MSGTYPE))
    assert _same(read_transitions(path), small)
    text = bag_info(path).format()
    assert "Topic: /gizmo | Type: acme_msgs/msg/Gizmo | Count: %d | Serialization Format: cdr" % len(rows) in text
    assert f"Transitions:       {len(rows)} in 4 episodes" in text


def test_bag_info_unknown_types_and_service_events(tmp_path):
    path = tmp_path / "other"
    with Writer(path, version=9) as writer:
        gizmo = writer.add_connection("/gizmo", "acme_msgs/msg/Gizmo", msgdef="int32 x", rihs01=FAKE_HASH)
        srv = writer.add_connection(
            "/reset/_service_event", "std_srvs/srv/Empty_Event", msgdef="uint8 x", rihs01=FAKE_HASH
        )
        for i in range(3):
            writer.write(gizmo, 10**9 + i, b"\x00\x01\x00\x00\x05\x00\x00\x00")
        writer.write(srv, 2 * 10**9, b"\x00\x01\x00\x00\x00")
    info = bag_info(path)
    assert [(t.name, t.msgtype, t.count) for t in info.topics] == [("/gizmo", "acme_msgs/msg/Gizmo", 3)]
    assert [(t.name, t.msgtype, t.count) for t in info.services] == [("/reset", "std_srvs/srv/Empty", 1)]
    text = info.format()
    for line in ("Storage id:        sqlite3", "Messages:          4", "Duration:          1.000000000s", "Service:           1"):
        assert line in text
    assert "Transitions" not in text


@pytest.mark.parametrize("name", ["rec.db3", "rec.mcap", "rec_dir"])
def test_bag_writer_is_a_bag_after_every_flush(tmp_path, small, name):
    """The recorder's writer: the bag is at its path from the start, and after each flush
    rosbags and read_transitions open it with exactly what was flushed."""
    rows = small.to_rows()
    path = tmp_path / name
    bag = BagWriter(path, flush_interval=3600)  # flushes only when asked here
    bag.add_topic(TRANSITION_TOPIC, TRANSITION_MSGTYPE)
    bag.add_topic("/pusher/state", "sensor_msgs/msg/JointState")
    payloads = encode_transition_rows(rows[:37])
    for i, payload in enumerate(payloads[:20]):
        bag.write(TRANSITION_TOPIC, 5_000 + i, payload)
    bag.flush()
    for i, payload in enumerate(payloads[20:], start=20):
        bag.write(TRANSITION_TOPIC, 5_000 + i, payload)
    assert np.array_equal(read_transitions(path).to_rows(), rows[:20])  # the unflushed 17 are pending
    with Reader(path) as reader:
        assert reader.message_count == 20
    bag.close()
    bag.close()  # idempotent
    assert np.array_equal(read_transitions(path).to_rows(), rows[:37])
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]  # no sidecars once closed


@pytest.mark.parametrize("name", ["empty.mcap", "empty_dir"])
def test_bag_writer_zero_messages(tmp_path, name):
    with BagWriter(tmp_path / name, storage=None) as bag:
        bag.add_topic("/pusher/state", "sensor_msgs/msg/JointState")
    with Reader(tmp_path / name) as reader:
        assert reader.message_count == 0
    assert bag_info(tmp_path / name).message_count == 0


def test_bag_writer_closes_on_interrupt(tmp_path, small):
    path = tmp_path / "rec_dir"
    with pytest.raises(KeyboardInterrupt):
        with BagWriter(path, storage="mcap") as bag:
            bag.add_topic(TRANSITION_TOPIC, TRANSITION_MSGTYPE)
            for i, payload in enumerate(encode_transition_rows(small.to_rows()[:5])):
                bag.write(TRANSITION_TOPIC, i, payload)
            raise KeyboardInterrupt
    assert len(read_transitions(path)) == 5


def test_shipped_bag_is_the_chapter_dataset():
    shipped = REPO / "bags" / "mix.db3"
    assert shipped.stat().st_size < 10 * 2**20
    assert _same(read_transitions(shipped), collect_transitions(200, 0.3, 0))
