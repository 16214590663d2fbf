"""Every way a bag can be wrong ends in one line naming the file, never a traceback."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.rosbag2 import Writer

from offline_rl_core.commands import cli
from offline_rl_core.data.bag import (
    TRANSITION_MSGTYPE, TRANSITION_TOPIC, BagWriter, encode_transition_rows, read_transitions, typestore,
    write_transitions,
)
from offline_rl_core.data.bag import writer as bag_writer
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.common.errors import UserError
from offline_rl_core.data.transitions import LAYOUT_SLICES


@pytest.fixture(scope="module")
def small():
    return collect_transitions(2, 0.5, 3)


def _refused(path, match: str) -> str:
    with pytest.raises(UserError) as info:
        read_transitions(path)
    message = str(info.value)
    assert "\n" not in message and str(path) in message and match in message, message
    return message


def _cli_refused(capsys, path, match: str) -> None:
    assert cli.main(["bag-info", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("offline-rl: error: ") and str(path) in err and match in err, err


def test_missing_path(tmp_path, capsys):
    _refused(tmp_path / "nope.db3", "no such file")
    _cli_refused(capsys, tmp_path / "nope.db3", "no such file")


def test_not_a_bag(tmp_path, capsys):
    text = tmp_path / "notes.txt"
    text.write_text("hello\n")
    _refused(text, "not a rosbag2 bag")
    _cli_refused(capsys, text, "not a rosbag2 bag")
    plain_dir = tmp_path / "plain"
    plain_dir.mkdir()
    _cli_refused(capsys, plain_dir, "no metadata.yaml")
    fake = tmp_path / "fake.db3"
    fake.write_text("hello\n")
    _cli_refused(capsys, fake, "corrupt")


@pytest.mark.parametrize("name", ["t.db3", "t.mcap"])
def test_truncated_storage(tmp_path, capsys, small, name):
    good = tmp_path / name
    write_transitions(good, small)
    data = good.read_bytes()
    for cut in (len(data) // 3, len(data) - 100):
        bad = tmp_path / f"cut{cut}{good.suffix}"
        bad.write_bytes(data[:cut])
        with pytest.raises(UserError) as info:
            read_transitions(bad)
        assert str(bad) in str(info.value) and "\n" not in str(info.value)
    _cli_refused(capsys, bad, "truncated")


def test_empty_bag(tmp_path):
    with BagWriter(tmp_path / "empty.db3") as bag:
        bag.add_topic(TRANSITION_TOPIC, TRANSITION_MSGTYPE)
    _refused(tmp_path / "empty.db3", "empty bag")


def test_bag_without_transition_topic(tmp_path):
    path = tmp_path / "other.db3"
    with BagWriter(path) as bag:
        bag.add_topic("/b", "std_msgs/msg/Float32MultiArray")
        bag.add_topic("/a", "std_msgs/msg/Float32MultiArray")
        bag.write("/a", 1, encode_transition_rows(np.zeros((1, 25), np.float32))[0])
        bag.write("/b", 2, encode_transition_rows(np.zeros((1, 25), np.float32))[0])
    message = _refused(path, "has no /pusher/transition topic (found: /a, /b)")
    assert "offline-rl collect" in message


def test_unknown_layout(tmp_path, capsys):
    ts = typestore()
    Msg, Layout, Dim = (ts.types[f"std_msgs/msg/{n}"] for n in ("Float32MultiArray", "MultiArrayLayout", "MultiArrayDimension"))
    msg = Msg(layout=Layout(dim=[Dim(label="x", size=25, stride=25)], data_offset=0), data=np.zeros(25, np.float32))
    path = tmp_path / "layout"
    with Writer(path, version=9) as writer:
        conn = writer.add_connection(TRANSITION_TOPIC, TRANSITION_MSGTYPE, typestore=ts)
        writer.write(conn, 1, ts.serialize_cdr(msg, TRANSITION_MSGTYPE))
    message = _refused(path, "unknown layout [x 25]")
    assert TRANSITION_TOPIC in message and "expected the fields [obs, action, reward, next_obs" in message
    assert cli.main(["bag-info", str(path)]) == 0  # info still lists the bag
    assert "not usable" in capsys.readouterr().out


def test_wrong_message_type(tmp_path):
    path = tmp_path / "wrongtype.db3"
    with BagWriter(path) as bag:
        bag.add_topic(TRANSITION_TOPIC, "std_msgs/msg/String")
        bag.write(TRANSITION_TOPIC, 1, b"\x00\x01\x00\x00\x01\x00\x00\x00\x00")
    _refused(path, "expected std_msgs/msg/Float32MultiArray")


def test_nan_rows(tmp_path, small):
    rows = small.to_rows()
    rows[[3, 8], LAYOUT_SLICES["reward"]] = np.nan
    rows[8, LAYOUT_SLICES["next_obs"].start] = np.inf
    path = tmp_path / "nan.db3"
    with BagWriter(path) as bag:
        bag.add_topic(TRANSITION_TOPIC, TRANSITION_MSGTYPE)
        for i, payload in enumerate(encode_transition_rows(rows)):
            bag.write(TRANSITION_TOPIC, i, payload)
    _refused(path, f"2 of {len(rows)} /pusher/transition rows hold NaN or inf (in fields reward, next_obs)")
    with pytest.raises(UserError, match="NaN"):
        write_transitions(tmp_path / "nan2.db3", rows)
    assert not (tmp_path / "nan2.db3").exists()


def test_failed_write_leaves_existing_bag_untouched(tmp_path, small, monkeypatch):
    path = tmp_path / "keep.db3"
    write_transitions(path, small)
    before = path.read_bytes()

    class Boom(RuntimeError):
        pass

    def exploding_write(self, connection, timestamp, data):
        if timestamp > bag_writer.TRANSITION_START_NS + 50 * bag_writer.TRANSITION_PERIOD_NS:
            raise Boom("disk on fire")
        return original(self, connection, timestamp, data)

    original = Writer.write
    monkeypatch.setattr(Writer, "write", exploding_write)
    for target in (path, tmp_path / "new.mcap", tmp_path / "newdir"):
        with pytest.raises(Boom):
            write_transitions(target, collect_transitions(3, 0.0, 1))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.db3"]


def test_write_refuses_missing_parent_and_recorder_refuses_existing(tmp_path, small):
    with pytest.raises(UserError, match="does not exist"):
        write_transitions(tmp_path / "no" / "x.db3", small)
    with pytest.raises(UserError, match="does not match"):
        write_transitions(tmp_path / "x.db3", small, storage="mcap")
    write_transitions(tmp_path / "x.db3", small)
    with pytest.raises(UserError, match="exists already"):
        BagWriter(tmp_path / "x.db3")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.db3"]
