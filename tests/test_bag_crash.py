"""A recording survives its process being killed; `offline-rl bag repair`; split bags.

The writer here runs in a child process killed by SIGKILL while it records: what it had
flushed must be readable where it wrote it, by our readers, by rosbags and (MCAP) by the
MCAP reference reader, with no repair step unless the kill cut a flush in half (MCAP),
and then after `offline-rl bag repair`.
"""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Reader

from offline_rl_core.commands import cli
from offline_rl_core.data.bag import (
    TRANSITION_MSGTYPE, TRANSITION_TOPIC, BagWriter, bag_info, encode_transition_rows, read_transitions, repair_bag,
    write_transitions,
)
from offline_rl_core.data.bag.reader import read_transition_rows
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.common.errors import UserError

REPO = Path(__file__).resolve().parents[1]
ROWS = 3000

# The child: writes ROWS transitions, flushing every 40 and printing how many are flushed.
CHILD = """
import sys
import numpy as np
from offline_rl_core.data.bag import BagWriter, encode_transition_rows
rows = np.random.default_rng(0).uniform(-1, 1, (%d, 25)).astype(np.float32)
path, storage, split = sys.argv[1], sys.argv[2] or None, float(sys.argv[3])
with BagWriter(path, storage, flush_interval=3600, max_bag_duration=split) as bag:
    bag.add_topic("/pusher/transition", "std_msgs/msg/Float32MultiArray")
    bag.add_topic("/pusher/state", "sensor_msgs/msg/JointState")
    print("ready", flush=True)
    for i, payload in enumerate(encode_transition_rows(rows)):
        bag.write("/pusher/transition", 10**9 + i * 10**6, payload)
        if i %% 40 == 39:
            bag.flush()
            print(i + 1, flush=True)
    print("done", flush=True)
""" % ROWS


def _child_rows() -> np.ndarray:
    return np.random.default_rng(0).uniform(-1, 1, (ROWS, 25)).astype(np.float32)


def _records(path: Path) -> int:
    """Messages the MCAP reference reader finds, checking every CRC."""
    from mcap.reader import make_reader

    files = sorted(path.glob("*.mcap")) if path.is_dir() else [path]
    total = 0
    for file in files:
        with file.open("rb") as f:
            reader = make_reader(f, validate_crcs=True)
            total += sum(1 for _ in reader.iter_messages())
    return total


@pytest.mark.parametrize(
    "name,storage,split,after",
    [("k.db3", "", 0, 7), ("k.mcap", "", 0, 11), ("kdir", "", 0.2, 23), ("kdirm", "mcap", 0.2, 29)],
)
def test_sigkill_keeps_every_flush(tmp_path, name, storage, split, after):
    path = tmp_path / name
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(path), storage, str(split)], stdout=subprocess.PIPE, text=True, cwd=REPO)
    try:
        assert child.stdout.readline().strip() == "ready"
        flushed = 0
        while flushed < after * 40:  # kill it after some flushes, wherever it is then
            flushed = int(child.stdout.readline())
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.wait()
    lines = child.stdout.read().split()
    flushed = max([flushed] + [int(x) for x in lines if x.isdigit()])
    try:
        rows = read_transition_rows(path)
    except UserError as exc:  # only MCAP, killed inside the two system calls of a flush
        assert name.endswith("m") or name.endswith(".mcap"), exc
        assert "bag repair" in str(exc) and "\n" not in str(exc)
        assert repair_bag(path)
        rows = read_transition_rows(path)
    assert len(rows) >= flushed and np.array_equal(rows, _child_rows()[: len(rows)])
    with Reader(path) as reader:  # rosbags itself, as the kill left it (or repaired)
        assert reader.message_count >= flushed
    if "m" in storage or name.endswith(".mcap"):
        assert _records(path) == len(rows)
    if split:
        assert len(bag_info(path).files) > 1


def test_quiet_topic_is_flushed_by_the_interval(tmp_path):
    """One message and nothing after: it reaches the disk within the flush interval."""
    path = tmp_path / "quiet.db3"
    rows = collect_transitions(1, 1.0, 0).to_rows()[:1]
    with BagWriter(path, flush_interval=0.05) as bag:
        bag.add_topic(TRANSITION_TOPIC, TRANSITION_MSGTYPE)
        bag.write(TRANSITION_TOPIC, 1, encode_transition_rows(rows)[0])
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            with Reader(path) as reader:
                if reader.message_count == 1:
                    break
            time.sleep(0.02)
        else:
            pytest.fail("the message was not flushed")
        assert np.array_equal(read_transition_rows(path), rows)


def _small_rows():
    return collect_transitions(3, 0.5, 4).to_rows()


def _write(path, rows, storage=None, flush_every=50, **kw) -> BagWriter:
    bag = BagWriter(path, storage, flush_interval=3600, **kw)
    bag.add_topic(TRANSITION_TOPIC, TRANSITION_MSGTYPE)
    for i, payload in enumerate(encode_transition_rows(rows)):
        bag.write(TRANSITION_TOPIC, 10**9 + i * 20_000_000, payload)
        if i % flush_every == flush_every - 1:
            bag.flush()
    return bag


def test_repair_mcap_cut_anywhere(tmp_path, capsys):
    rows = _small_rows()
    whole = tmp_path / "whole.mcap"
    _write(whole, rows).close()
    data = whole.read_bytes()
    cut_at = sorted({len(data) - 1, len(data) - 40, len(data) // 2, len(data) // 3, 2000, 30})
    for cut in cut_at:
        path = tmp_path / f"cut{cut}.mcap"
        path.write_bytes(data[:cut])
        with pytest.raises(UserError, match="bag repair"):
            read_transitions(path)
        assert cli.main(["bag", "repair", str(path)]) == 0
        out = capsys.readouterr().out
        assert "wrote the summary" in out
        with Reader(path) as reader:
            kept = reader.message_count
        assert _records(path) == kept
        if kept:
            got = read_transition_rows(path)
            assert len(got) == kept and np.array_equal(got, rows[:kept])
        assert repair_bag(path) == []  # whole now: nothing more to do
    assert kept > len(rows) - 50  # the last cut lost at most the last flush


def test_repair_sqlite_folds_a_left_wal(tmp_path):
    """A writer killed between a commit and its checkpoint leaves the commit in x.db3-wal:
    WAL-aware readers (ours, sqlite, rosbag2) see it; repair folds it into the file for
    readers that open it immutable (rosbags)."""
    rows = _small_rows()
    path = tmp_path / "w.db3"
    code = f"""
import os
from offline_rl_core.data.bag import BagWriter, encode_transition_rows, storage_sqlite
from offline_rl_core.data.collect import collect_transitions
payloads = encode_transition_rows(collect_transitions(3, 0.5, 4).to_rows()[:150])
bag = BagWriter({str(path)!r}, flush_interval=3600)
bag.add_topic("/pusher/transition", "std_msgs/msg/Float32MultiArray")
for i, payload in enumerate(payloads):
    bag.write("/pusher/transition", 10**9 + i, payload)
    if i == 99:
        bag.flush()
        storage_sqlite.SqliteFileWriter._checkpoint = lambda self: None  # killed before it
bag.flush()
os._exit(0)  # no close: as a kill leaves it
"""
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO)
    assert Path(f"{path}-wal").stat().st_size > 0
    assert np.array_equal(read_transition_rows(path), rows[:150])
    assert "w.db3-wal holds commits not yet in w.db3" in bag_info(path).format()
    with Reader(path) as reader:
        assert reader.message_count == 100  # immutable: the WAL is invisible to it
    done = repair_bag(path)
    assert any("write-ahead log" in line for line in done)
    assert not Path(f"{path}-wal").exists()
    with Reader(path) as reader:
        assert reader.message_count == 150
    con = sqlite3.connect(path)
    meta = con.execute("SELECT metadata FROM metadata").fetchone()[0]
    con.close()
    assert "message_count: 150" in meta


def test_sqlite_digest_catches_what_sqlite_cannot(tmp_path):
    """A changed payload byte, stamp or topic id reads back as an error, not a new row."""
    rows = _small_rows()[:60]
    good = tmp_path / "good.db3"
    _write(good, rows).close()
    for n, statement in enumerate([
        "UPDATE messages SET data = CAST(data AS BLOB) || x'00' WHERE id = 7",
        "UPDATE messages SET timestamp = timestamp + 1 WHERE id = 9",
        "UPDATE messages SET topic_id = 5 WHERE id = 11",
    ]):
        bad = tmp_path / f"bad{n}.db3"
        bad.write_bytes(good.read_bytes())
        con = sqlite3.connect(bad)
        con.execute(statement)
        con.commit()
        con.close()
        with pytest.raises(UserError, match="corrupt") as info:
            read_transitions(bad)
        assert str(bad) in str(info.value) and "\n" not in str(info.value)


def test_repair_sqlite_without_metadata_table_and_dir_without_yaml(tmp_path):
    rows = _small_rows()
    bag_dir = tmp_path / "bag"
    write_transitions(bag_dir, rows)  # rosbags' writer: bag/bag.db3 + metadata.yaml
    (bag_dir / "metadata.yaml").unlink()
    con = sqlite3.connect(bag_dir / "bag.db3")
    con.execute("DROP TABLE metadata")
    con.commit()
    con.close()
    # the storage file describes itself: the bag reads as it is, and repair writes the yaml
    assert np.array_equal(read_transitions(bag_dir).to_rows(), rows)
    done = repair_bag(bag_dir)
    assert any("rebuilt metadata.yaml" in line for line in done) and any("wrote the metadata" in line for line in done)
    assert np.array_equal(read_transitions(bag_dir).to_rows(), rows)
    with Reader(bag_dir) as reader:
        assert reader.message_count == len(rows)
    assert repair_bag(bag_dir) == []


def test_repair_refuses_a_bag_being_recorded_and_what_is_not_a_bag(tmp_path, capsys):
    bag = _write(tmp_path / "live", _small_rows()[:10])
    with pytest.raises(UserError, match="being recorded"):
        repair_bag(tmp_path / "live")
    bag.close()
    assert repair_bag(tmp_path / "live") == []
    (tmp_path / "notes.txt").write_text("x")
    assert cli.main(["bag", "repair", str(tmp_path / "notes.txt")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "not a rosbag2 bag" in err


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_split_bag_is_one_bag(tmp_path, storage):
    rows = _small_rows()
    path = tmp_path / "split"
    # stamps 20 ms apart: a new file every 1.0 s of stamps = 50 messages
    _write(path, rows, storage, max_bag_duration=1.0, flush_every=7).close()
    files = sorted(p.name for p in path.iterdir())
    n_files = -(-len(rows) // 50)
    suffix = ".db3" if storage == "sqlite3" else ".mcap"
    assert files == sorted([f"split_{i}{suffix}" for i in range(n_files)] + ["metadata.yaml"])
    assert np.array_equal(read_transitions(path).to_rows(), rows)
    info = bag_info(path)
    assert info.files == [f"split_{i}{suffix}" for i in range(n_files)] and info.message_count == len(rows)
    with Reader(path) as reader:
        assert reader.message_count == len(rows)
        assert [f["message_count"] for f in reader.storage.files] == [50] * (n_files - 1) + [len(rows) - 50 * (n_files - 1)]
    shim = subprocess.run([str(REPO / ".venv" / "bin" / "ros2"), "bag", "info", str(path)], capture_output=True, text=True)
    if shim.returncode == 0:  # `ros2 bag info` (the shim, or the real one where installed)
        assert f"Messages:          {len(rows)}" in shim.stdout


def test_split_by_size_and_bad_settings(tmp_path):
    rows = collect_transitions(20, 0.5, 1).to_rows()
    _write(tmp_path / "big", rows, max_bag_size=120_000, flush_every=100).close()
    sizes = [p.stat().st_size for p in sorted((tmp_path / "big").glob("*.db3"))]
    assert len(sizes) > 1
    assert np.array_equal(read_transitions(tmp_path / "big").to_rows(), rows)
    with pytest.raises(UserError, match="needs a bag directory"):
        BagWriter(tmp_path / "one.db3", max_bag_duration=5)
    with pytest.raises(UserError, match="sqlite3 minimum"):
        BagWriter(tmp_path / "tiny", max_bag_size=1000)
    with pytest.raises(UserError, match="flush interval"):
        BagWriter(tmp_path / "never", flush_interval=0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big"]


def test_leftover_wal_is_not_adopted(tmp_path):
    """A new recording never applies another recording's stray WAL to its file."""
    Path(f"{tmp_path / 'x.db3'}-wal").write_bytes(b"old")
    with pytest.raises(UserError, match="left from an earlier recording"):
        BagWriter(tmp_path / "x.db3")
    with BagWriter(tmp_path / "x.db3", overwrite=True) as bag:
        bag.add_topic(TRANSITION_TOPIC, TRANSITION_MSGTYPE)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.db3"]


@pytest.mark.parametrize("name", ["whole.db3", "whole.mcap", "whole_dir"])
def test_repair_leaves_a_whole_bag_alone(tmp_path, name):
    """A bag that needs nothing (here from rosbags' writer) is not rewritten."""
    path = tmp_path / name
    write_transitions(path, _small_rows())
    files = sorted(path.iterdir()) if path.is_dir() else [path]
    before = [f.read_bytes() for f in files]
    assert repair_bag(path) == []
    assert [f.read_bytes() for f in files] == before
