"""Every valid bag reads the same rows, whatever writer options made it.

The MCAP specification makes the whole summary optional (statistics, repeated channels and
schemas, chunk and message indexes); rosbag2's MCAP plugin has storage presets and
rosbag2's sqlite3 plugin a ``resilient`` one; a bag directory may lack its metadata.yaml.
Each layout here is written by the real writer (Foxglove's ``mcap`` library) with the
messages of bags/mix.db3, and read back through read_transitions, bag-info, `offline-rl
bag repair`, `offline-rl dataset --from-topics` and the trainer.
"""

from __future__ import annotations

import json
import random
import struct
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import NonSeekingReader
from mcap.writer import CompressionType
from rosbags.rosbag2 import Reader

from offline_rl_core.commands import cli
from offline_rl_core.common.errors import UserError
from offline_rl_core.data.bag import (
    TRANSITION_TOPIC, bag_info, decode_transition_payloads, read_transitions, repair_bag,
)
from offline_rl_core.data.bag.mcap_reader import CheckedMcapReader
from offline_rl_core.data.raw_topics import transitions_from_topics

from bag_layouts import (
    MIX, ROSBAG2_PRESETS, SQLITE_PRESETS, Message, bag_directory, messages_of, spec_valid, write_mcap,
    write_rosbag2_mcap, write_rosbag2_sqlite, writer_layouts,
)
from raw_topic_bags import record_raw_bag

MESSAGES = messages_of(MIX, limit=300)
ROWS = decode_transition_payloads([m.data for m in MESSAGES])
LAYOUTS = writer_layouts()
NO_SUMMARY = "no_statistics-no_summary_offsets-no_repeat_channels-no_repeat_schemas-index_none"
UNCHUNKED_NO_SUMMARY = "no_chunking-" + NO_SUMMARY
SPEC = "pusher_reach"  # the task file (built in) says how the raw topics join
FAST = settings(max_examples=120, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def reference_records(path: Path) -> int:
    """Messages Foxglove's own streaming reader finds in a file, checking its records and
    CRCs: the file is what its writer meant. (Its indexed reader, like rosbags', trusts the
    summary, so it cannot be the judge here.)"""
    with path.open("rb") as f:
        return sum(1 for _ in NonSeekingReader(f, validate_crcs=True).iter_messages())


def check_reads_the_messages(path: Path, messages: list[Message] = MESSAGES, rows: np.ndarray = ROWS) -> None:
    """read_transitions gives the rows written; bag-info lists the topics, types, counts,
    start and end of the messages written; repair leaves the bag as it is."""
    assert np.array_equal(read_transitions(path).to_rows(), rows)
    info = bag_info(path)
    expected = {}
    for m in messages:
        name, msgtype, count = expected.get(m.topic, (m.topic, m.msgtype, 0))
        expected[m.topic] = (name, msgtype, count + 1)
    assert [(t.name, t.msgtype, t.count) for t in info.topics] == sorted(expected.values())
    assert info.message_count == len(messages)
    assert (info.start_ns, info.end_ns) == (min(m.stamp for m in messages), max(m.stamp for m in messages))
    assert info.transitions == len(rows) and info.transition_problem is None
    files = sorted(path.iterdir()) if path.is_dir() else [path]
    before = [f.read_bytes() for f in files]
    without_yaml = path.is_dir() and not (path / "metadata.yaml").is_file()
    done = repair_bag(path)
    if without_yaml:  # repair writes it; the storage files stay as they are
        assert done and "rebuilt metadata.yaml" in done[-1]
        (path / "metadata.yaml").unlink()
    else:
        assert done == []
    assert [f.read_bytes() for f in files] == before


def test_the_layouts_are_the_full_cross_product_of_the_writer_options():
    assert len(LAYOUTS) == 2**5 * 3 and len(set(map(str, LAYOUTS.values()))) == len(LAYOUTS)
    assert sum(map(spec_valid, LAYOUTS.values())) == 64
    assert np.array_equal(ROWS, read_transitions(MIX).to_rows()[:300])


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_every_mcap_writer_layout(tmp_path, layout):
    """The 64 valid layouts, and the 32 that break a summary rule of the spec (read as well)."""
    path = write_mcap(tmp_path / f"{layout}.mcap", MESSAGES, **LAYOUTS[layout])
    assert reference_records(path) == len(MESSAGES)
    check_reads_the_messages(path)


@pytest.mark.parametrize("preset", list(ROSBAG2_PRESETS))
def test_rosbag2_mcap_presets(tmp_path, preset):
    path = write_rosbag2_mcap(tmp_path / f"{preset}.mcap", MESSAGES, preset, chunk_size=4096)
    assert reference_records(path) == len(MESSAGES)
    check_reads_the_messages(path)


@pytest.mark.parametrize("compression", [CompressionType.NONE, CompressionType.LZ4, CompressionType.ZSTD],
                         ids=["none", "lz4", "zstd"])
@pytest.mark.parametrize("layout", ["default", NO_SUMMARY, "no_repeat_channels-index_chunk"])
def test_chunk_compressions(tmp_path, layout, compression):
    path = write_mcap(tmp_path / "c.mcap", MESSAGES, compression=compression, **LAYOUTS[layout])
    check_reads_the_messages(path)


def test_a_full_summary_is_read_and_only_a_lacking_one_scanned(tmp_path):
    """The summary is trusted when it holds what reading needs, and scanned around otherwise."""
    def gaps(layout: str) -> tuple[str, ...]:
        path = write_mcap(tmp_path / f"{layout}.mcap", MESSAGES, **LAYOUTS[layout])
        reader = CheckedMcapReader(path)
        reader.open()
        try:
            return reader.scanned_because
        finally:
            reader.close()

    assert gaps("default") == () and gaps("no_summary_offsets") == () and gaps("no_chunking") == ()
    assert gaps(NO_SUMMARY) == ("no summary",)
    assert gaps("no_statistics") == ("no statistics",)
    assert gaps("no_repeat_channels") == ("channels not repeated",)
    assert gaps("no_repeat_schemas") == ("schemas not repeated",)
    assert gaps("index_chunk") == ("no message index",) and gaps("index_none") == ("no chunk index",)


@pytest.mark.parametrize("layout", ["no_chunking", UNCHUNKED_NO_SUMMARY, "default", NO_SUMMARY])
def test_messages_out_of_stamp_order_and_other_records(tmp_path, layout):
    """A writer may put messages out of stamp order (and rosbags refuses them outside
    chunks), and attachments and metadata between them: rows come in stamp order, as from
    sqlite3, and the other records are passed over."""
    shuffled = MESSAGES[:]
    random.Random(0).shuffle(shuffled)
    path = tmp_path / "shuffled.mcap"
    write_mcap(path, shuffled, chunk_size=2000, extra_records=True, **LAYOUTS[layout])
    assert reference_records(path) == len(MESSAGES)
    check_reads_the_messages(path)


# ------------------------------------------------------------------ bad files stay refused
def _refused(path: Path, *words: str) -> str:
    with pytest.raises(UserError) as info:
        read_transitions(path)
    message = str(info.value)
    assert "\n" not in message and str(path) in message and all(w in message for w in words), message
    return message


@pytest.mark.parametrize("layout", [NO_SUMMARY, "no_statistics", "index_chunk"])
def test_scanned_files_truncated_or_corrupt_are_refused_in_one_line(tmp_path, layout):
    good = write_mcap(tmp_path / "good.mcap", MESSAGES, enable_data_crcs=True, **LAYOUTS[layout])
    data = good.read_bytes()

    def variant(name: str, content: bytes) -> Path:
        path = tmp_path / name
        path.write_bytes(content)
        return path

    _refused(variant("cut.mcap", data[: len(data) // 2]), "bag repair")
    _refused(variant("magic.mcap", b"\x89MCAQ" + data[5:]), "magic")
    chunk = 8 + 9 + struct.unpack_from("<Q", data, 9)[0]  # the record after the Header: the first chunk
    assert data[chunk] == 0x06
    flipped = bytearray(data)
    flipped[chunk + 9 + 60] ^= 0x10  # inside its records (CRC-checked)
    _refused(variant("flip.mcap", bytes(flipped)), "corrupt")
    footer_crc = bytearray(data)
    footer_crc[-9] ^= 0x01
    _refused(variant("footer.mcap", bytes(footer_crc)), "corrupt", "checksum")


def test_a_truncated_scanned_file_is_repaired_to_a_prefix(tmp_path, capsys):
    data = write_mcap(tmp_path / "whole.mcap", MESSAGES, **LAYOUTS[NO_SUMMARY]).read_bytes()
    for cut, kept in ((len(data) // 3, "some"), (len(data) - 20, "all")):  # in the data; in the footer
        path = tmp_path / f"cut{cut}.mcap"
        path.write_bytes(data[:cut])
        _refused(path, "bag repair")
        assert cli.main(["bag", "repair", str(path)]) == 0
        assert "wrote the summary" in capsys.readouterr().out
        rows = read_transitions(path).to_rows()
        assert (0 < len(rows) < len(ROWS)) if kept == "some" else len(rows) == len(ROWS)
        assert np.array_equal(rows, ROWS[: len(rows)])
        assert reference_records(path) == len(rows)
        assert repair_bag(path) == []


def _fuzz_bytes(layout: str) -> bytes:
    """A small file of the layout, chunk and data-section CRCs on: what damage can be caught."""
    with tempfile.TemporaryDirectory() as tmp:
        return write_mcap(Path(tmp) / "f.mcap", MESSAGES[:60], chunk_size=1500, enable_data_crcs=True,
                          **LAYOUTS[layout]).read_bytes()


FUZZ = {name: _fuzz_bytes(name) for name in ("default", NO_SUMMARY)}


@FAST
@pytest.mark.parametrize("layout", list(FUZZ))
@given(bits=st.lists(st.integers(0, 10**9), min_size=1, max_size=3), cut=st.sampled_from([None, 0.3, 0.7, 0.999]))
def test_flipped_or_cut_files_give_the_rows_or_one_line(tmp_path, layout, bits, cut):
    """Read from the summary or scanned, a damaged file gives the rows written or one line
    naming it, never other rows or a traceback."""
    assert_rows_or_one_line(tmp_path, layout, bits, cut)


def assert_rows_or_one_line(tmp_path, layout: str, bits, cut: float | None) -> None:
    """The ``layout``'s file with ``bits`` flipped and cut at ``cut`` of its length reads as
    the rows written or fails in one line naming it."""
    data = bytearray(FUZZ[layout])
    for at in sorted({b % (len(data) * 8) for b in bits}):
        data[at // 8] ^= 1 << (at % 8)
    if cut is not None:
        data = data[: int(cut * len(data))]
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(data))
    try:
        got = read_transitions(path).to_rows()
    except UserError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc), exc
        return
    assert np.array_equal(got, ROWS[:60])


# ------------------------------------------------------------------ sqlite3 and bag directories
@pytest.mark.parametrize("preset", list(SQLITE_PRESETS))
def test_rosbag2_sqlite_presets(tmp_path, preset):
    path = write_rosbag2_sqlite(tmp_path / f"{preset}.db3", MESSAGES, preset)
    header = path.read_bytes()[:20]
    assert header[18:20] == (b"\x02\x02" if preset == "resilient" else b"\x01\x01")  # WAL mode, or not
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # closed: no -wal left
    check_reads_the_messages(path)
    assert bag_info(path).ros_distro == "kilted"


def _split(tmp_path: Path, storage: str, files: int, with_yaml: bool, layout: str = NO_SUMMARY) -> Path:
    bag = tmp_path / f"split_{storage}_{files}"
    bag.mkdir()
    bounds = [len(MESSAGES) * i // files for i in range(files + 1)]
    parts = [MESSAGES[a:b] for a, b in zip(bounds, bounds[1:])]
    paths = []
    for i, part in enumerate(parts):
        if storage == "mcap":
            paths.append(write_mcap(bag / f"{bag.name}_{i}.mcap", part, **LAYOUTS[layout]))
        else:
            paths.append(write_rosbag2_sqlite(bag / f"{bag.name}_{i}.db3", part, storage.removeprefix("sqlite3_")))
    return bag_directory(bag, paths, "mcap" if storage == "mcap" else "sqlite3", parts, with_yaml)


@pytest.mark.parametrize("with_yaml", [True, False], ids=["metadata.yaml", "no-metadata.yaml"])
@pytest.mark.parametrize("storage", ["mcap", "sqlite3_none", "sqlite3_resilient"])
def test_bag_directories_with_and_without_metadata_yaml(tmp_path, capsys, storage, with_yaml):
    bag = _split(tmp_path, storage, 11, with_yaml)  # x_0 ... x_10: split order, not name order
    check_reads_the_messages(bag)
    info = bag_info(bag)
    assert info.files == [f"{bag.name}_{i}.{'mcap' if storage == 'mcap' else 'db3'}" for i in range(11)]
    assert any("no metadata.yaml" in note for note in info.notes) != with_yaml
    assert cli.main(["bag-info", str(bag)]) == 0
    assert "Messages:          300" in capsys.readouterr().out
    if not with_yaml:  # repair writes the metadata.yaml that rosbags itself needs
        assert any("rebuilt metadata.yaml" in line for line in repair_bag(bag))
        with Reader(bag) as reader:
            assert reader.message_count == 300
        assert np.array_equal(read_transitions(bag).to_rows(), ROWS)


def test_a_directory_of_other_files_or_of_two_storages_is_refused(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("x")
    assert cli.main(["bag-info", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(tmp_path) in err and "no metadata.yaml and no .db3 or .mcap files" in err
    write_mcap(tmp_path / "a_0.mcap", MESSAGES[:10])
    write_rosbag2_sqlite(tmp_path / "a_1.db3", MESSAGES[10:20])
    _refused(tmp_path, "holds both sqlite3 and MCAP files")


# ------------------------------------------------------------------ the commands that read bags
RAW_LAYOUTS = ["default", NO_SUMMARY, UNCHUNKED_NO_SUMMARY, "no_repeat_schemas-index_chunk"]


@pytest.fixture(scope="module")
def raw_bag(tmp_path_factory) -> Path:
    """Raw robot topics (joint states, commands, targets) as an arm's log holds them."""
    path = tmp_path_factory.mktemp("raw") / "arm.db3"
    record_raw_bag(path, episodes=2, expert_frac=0.5, seed=11, sim_like=False)
    return path


@pytest.mark.parametrize("layout", RAW_LAYOUTS)
def test_dataset_from_topics_on_every_layout(tmp_path, raw_bag, layout):
    expected, _ = transitions_from_topics(raw_bag, SPEC)
    messages = messages_of(raw_bag)
    path = write_mcap(tmp_path / "arm.mcap", messages, **LAYOUTS[layout])
    rows = decode_transition_payloads([m.data for m in messages if m.topic == TRANSITION_TOPIC])
    check_reads_the_messages(path, messages, rows)
    out = tmp_path / "built.db3"
    assert cli.main(["dataset", "--from-topics", str(SPEC), str(path), str(out)]) == 0
    assert np.array_equal(read_transitions(out).to_rows(), expected.to_rows())


@pytest.mark.slow  # the trainer's first import of torch alone takes seconds
def test_the_trainer_sees_the_same_dataset_in_every_layout(tmp_path):
    def dataset_hash(bag: Path) -> str:
        out = tmp_path / f"run_{bag.name}"
        assert cli.main(["train", "--bag", str(bag), "--algo", "bc", "--steps", "2", "--eval-episodes", "0",
                         "--out", str(out)]) == 0
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["transitions"] == len(ROWS)
        return metrics["dataset_hash"]

    reference = dataset_hash(write_rosbag2_sqlite(tmp_path / "ref.db3", MESSAGES))
    bags = [write_mcap(tmp_path / f"{name}.mcap", MESSAGES, **LAYOUTS[name])
            for name in (NO_SUMMARY, UNCHUNKED_NO_SUMMARY, "no_repeat_channels-index_chunk")]
    bags += [write_rosbag2_mcap(tmp_path / "fastwrite.mcap", MESSAGES, "fastwrite"),
             write_rosbag2_sqlite(tmp_path / "resilient.db3", MESSAGES, "resilient"),
             _split(tmp_path, "mcap", 3, with_yaml=False)]
    for bag in bags:
        assert dataset_hash(bag) == reference, bag.name


def test_a_bit_flipped_mid_file_in_an_unindexed_mcap_is_not_read_as_a_cut_end(tmp_path):
    """Found by the fuzz test above in a CI run (bits=[436782202], no cut): a chunk's opcode
    flipped into a Footer's read as the file's end, and 17 of the 60 rows came back
    silently. A Footer anywhere but before the closing magic is corruption: one line."""
    assert_rows_or_one_line(tmp_path, "no_statistics-no_summary_offsets-no_repeat_channels-no_repeat_schemas-index_none",
                            [436782202], None)
