"""`offline-rl` given bad flags or paths: one line naming the flag or file and what was
expected, exit code 2, no traceback, and nothing already written lost or replaced."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest

from offline_rl_core.commands import cli

REPO = Path(__file__).resolve().parents[1]


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _one_error_line(capsys, *words: str) -> str:
    """The run's error: the last line on stderr (after any progress), the only one of its kind."""
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert "Traceback" not in err and lines[-1].startswith("offline-rl: error: "), err
    assert sum(line.startswith("offline-rl:") for line in lines) == 1, err
    assert all(w in lines[-1] for w in words), lines[-1]
    return lines[-1]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A 2-episode bag and a finished BC run on it (DIR/policy.pt, metrics.json)."""
    from offline_rl_core.data.bag import write_transitions
    from offline_rl_core.data.collect import collect_transitions

    root = tmp_path_factory.mktemp("cli_input")
    bag = root / "tiny.db3"
    write_transitions(bag, collect_transitions(2, 0.5, 0))
    run = root / "run"
    assert cli.main(["train", "--bag", str(bag), "--algo", "bc", "--steps", "2", "--batch-size", "8", "--hidden", "8",
                     "--eval-episodes", "0", "--out", str(run)]) == 0
    text = root / "text.db3"
    text.write_text("not a bag\n")
    return {"bag": bag, "run": run, "text": text}


def _train(tiny, *flags: str) -> int:
    return cli.main(["train", "--bag", str(tiny["bag"]), "--algo", "bc", "--steps", "2", "--batch-size", "8",
                     "--hidden", "8", "--eval-episodes", "0", "--out", str(tiny["run"]), *flags])


@pytest.mark.parametrize("flags, expected", [
    (("--gamma", "nan"), "--gamma must be in [0, 1], got nan"),
    (("--gamma", "5"), "--gamma must be in [0, 1]"),
    (("--tau", "-1"), "--tau must be in (0, 1]"),
    (("--algo", "iql", "--expectile", "2"), "--expectile must be in (0, 1)"),
    (("--beta", "0"), "--beta must be finite and > 0"),
    (("--alpha", "nan"), "--alpha must be finite and > 0"),
    (("--algo", "sac", "--target-entropy", "nan"), "--target-entropy must be finite"),
    (("--lr", "nan"), "--lr must be finite and > 0"),
    (("--steps", "-5"), "--steps must be >= 1, got -5"),
    (("--batch-size", "0"), "--batch-size must be >= 1"),
])
def test_flags_out_of_range_are_refused_naming_the_flag_and_keep_the_run(tiny, capsys, flags, expected):
    before = _sha(tiny["run"] / "policy.pt")
    assert _train(tiny, *flags) == 2
    _one_error_line(capsys, expected)
    assert _sha(tiny["run"] / "policy.pt") == before


def test_a_run_that_diverges_writes_nothing_and_keeps_the_previous_checkpoint(tiny, capsys):
    before = {p.name: _sha(p) for p in tiny["run"].iterdir()}
    assert _train(tiny, "--lr", "1e30") == 2
    _one_error_line(capsys, "bc diverged", "not finite", "nothing written but the event files of its curves")
    after = {p.name: _sha(p) for p in tiny["run"].iterdir()}
    assert {name: after.get(name) for name in before} == before  # no resume.pt left either
    added = set(after) - set(before)  # only the curves of the diverged run, to see where it went wrong
    assert len(added) == 1 and next(iter(added)).startswith("events.out.tfevents.")


def test_choice_flags_are_checked_before_the_bag_is_read(capsys):
    for flag in ("--lr-schedule", "--filter-by"):
        with pytest.raises(SystemExit) as exit_:
            cli.main(["train", "--bag", "no/such.db3", flag, "linear"])
        assert exit_.value.code == 2
        assert f"argument {flag}: invalid choice: 'linear'" in capsys.readouterr().err


@pytest.mark.parametrize("argv, flag", [
    (["collect", "--episodes", "1", "--out", "x.db3", "--seed", "-1"], "--seed"),
    (["eval", "--checkpoint", "x.pt", "--seed", "-1"], "--seed"),
    (["experiment", "--smoke", "--out", "x", "--seed", "-1"], "--seed"),
    (["experiment", "--smoke", "--out", "x", "--seeds", "0", "-1"], "--seeds"),
    (["train", "--bag", "x.db3", "--seed", "-1"], "--seed"),
    (["train", "--bag", "x.db3", "--eval-seed", "-1"], "--eval-seed"),
    (["train", "--bag", "x.db3", "--seed", str(2**32)], "--seed"),
    (["hil", "--seed", "-1"], "--seed"),
    (["hil", "--online", "--eval-seed", "-1"], "--eval-seed"),
])
def test_negative_seeds_are_refused_naming_the_flag(capsys, argv, flag):
    with pytest.raises(SystemExit) as exit_:
        cli.main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {flag}: expected a whole number from 0 to 4294967295" in err and "Traceback" not in err


def _unwritable_cases(tiny, tmp: Path):
    """(argv, the flag) whose output path cannot be written; each must fail before its work."""
    text, run, bag = tiny["text"], tiny["run"], tiny["bag"]
    a_dir = tmp / "a_dir"
    a_dir.mkdir()
    return [
        (["train", "--bag", str(bag), "--steps", "2", "--eval-episodes", "0", "--out", f"{text}/sub"], "--out"),
        (["train", "--bag", str(bag), "--steps", "2", "--eval-episodes", "0", "--out", str(text)], "--out"),
        (["eval", "--checkpoint", str(run), "--episodes", "2", "--json", f"{text}/x.json"], "--json"),
        (["eval", "--checkpoint", str(run), "--episodes", "2", "--json", str(a_dir)], "--json"),
        (["export-onnx", "--checkpoint", str(run), "--out", f"{text}/x.onnx"], "--out"),
        (["export-onnx", "--checkpoint", str(run), "--out", str(a_dir)], "--out"),
        (["experiment", "--smoke", "--out", str(text)], "--out"),
        (["bench", "--tiny", "--only", "decode", "--json", f"{text}/b.json"], "--json"),
        (["hil", "--out", f"{text}/hil"], "--out"),
    ]


def test_an_output_that_cannot_be_written_fails_in_one_line_before_the_work(tiny, tmp_path, capsys):
    before = _sha(tiny["text"])
    for argv, flag in _unwritable_cases(tiny, tmp_path):
        assert cli.main(argv) == 2, argv
        _one_error_line(capsys, flag)
    assert _sha(tiny["text"]) == before


def test_dataset_checks_its_report_path_before_writing_the_bag(tiny, tmp_path, capsys):
    out_bag = tmp_path / "d2.db3"
    argv = ["dataset", "--task", "pusher_reach", str(tiny["bag"]), str(out_bag), "--report", f"{tiny['text']}/r.json"]
    assert cli.main(argv) == 2
    _one_error_line(capsys, "--report", f"{tiny['text']} is a file, not a directory")
    assert not out_bag.exists()  # the rerun is not refused with "exists already"


def test_collect_never_replaces_a_file_that_is_not_a_bag(tiny, tmp_path, capsys):
    victim = tmp_path / "victim.db3"
    shutil.copy(tiny["text"], victim)
    assert cli.main(["collect", "--episodes", "1", "--out", str(victim)]) == 2
    _one_error_line(capsys, str(victim), "is not a rosbag2 sqlite3 bag file; not replacing it")
    assert victim.read_text() == "not a bag\n"
    assert cli.main(["collect", "--episodes", "1", "--out", f"{tiny['text']}/x.db3"]) == 2
    _one_error_line(capsys, f"{tiny['text']} is a file, not a directory")


def test_bench_only_with_no_group_is_refused(capsys):
    assert cli.main(["bench", "--tiny", "--only", ","]) == 2
    _one_error_line(capsys, "--only: expected some of train, decode, eval, serve, record, online")


def test_unreadable_checkpoints_say_what_they_are(tiny, tmp_path, capsys):
    good = (tiny["run"] / "policy.pt").read_bytes()
    cases = {"empty.pt": (b"", "the file is empty"),
             "text.pt": (b"101 not a checkpoint\n", "not a torch checkpoint"),
             "cut.pt": (good[: len(good) // 2], "truncated: the torch zip archive ends early"),
             "bag.db3": (tiny["bag"].read_bytes(), "an SQLite database, e.g. a rosbag2 .db3 bag, not a torch checkpoint")}
    for name, (data, words) in cases.items():
        (tmp_path / name).write_bytes(data)
        assert cli.main(["eval", "--checkpoint", str(tmp_path / name), "--episodes", "1"]) == 2
        line = _one_error_line(capsys, name, f"({words})")
        assert line.endswith(")"), line  # whole words, never cut mid-word


def test_hil_takes_its_defaults_by_mode_and_refuses_the_other_modes_flags(capsys, tmp_path, monkeypatch):
    from offline_rl_core.commands.hil import _resolve_mode_flags
    from offline_rl_core.pipelines.hil import PROJECT_BAG

    for argv, flags in ((["hil", "--online", "--rounds", "2", "--beta", "0.2"], "--rounds, --beta: only without --online"),
                        (["hil", "--utd", "2"], "--utd: only with --online"),
                        (["hil", "--bc-weight", "30", "--lr-decay"], "--bc-weight, --lr-decay: only with --online"),
                        (["hil", "--steer", "stick", "--offline-ratio", "0.25", "--corrector-noise", "0.2"],
                         "--steer, --offline-ratio, --corrector-noise: only with --online"),
                        (["hil", "--online", "--corrector-noise", "0.2", "--corrector", "none", "--out",
                          str(tmp_path / "o")], "--corrector-noise: the scripted corrector's shaky hand"),
                        (["hil", "--online", "--offline-ratio", "1.5", "--out", str(tmp_path / "o")],
                         "--offline-ratio must be in [0, 1], got 1.5"),
                        (["hil", "--online", "--patience", "0", "--out", str(tmp_path / "o")],
                         "--patience must be >= 1, got 0"),
                        (["hil", "--online", "--noise", "0.1"], "--noise: only without --online"),
                        (["hil", "--no-explore"], "--no-explore: only with --online"),
                        (["hil", "--action-labels"], "--action-labels: only with --online"),
                        (["hil", "--online", "--action-labels", "--out", str(tmp_path / "o")],
                         "--action-labels: over ROS only with --from-topics"),
                        (["hil", "--online", "--action-labels", "--in-process", "--corrector", "none", "--out",
                          str(tmp_path / "o")], "--action-labels: the scripted corrector labels the states"),
                        (["hil", "--online", "--grace-steps", "-1", "--out", str(tmp_path / "o")],
                         "--grace-steps must be >= 0, got -1"),
                        (["hil", "--online", "--steer", "stick", "--corrector", "none", "--out", str(tmp_path / "o")],
                         "--steer stick: how the scripted corrector takes over; only with --corrector scripted"),
                        (["hil", "--online", "--steer", "stick", "--task", "pusher_push", "--env-steps", "60",
                          "--in-process", "--out", str(tmp_path / "o")],
                         "task pusher_push's is goal - puck")):
        assert cli.main(argv) == 2
        _one_error_line(capsys, flags)
    monkeypatch.chdir(tmp_path)  # not the project: the default bag is still found
    parser = cli.build_parser()
    explicit = parser.parse_args(["hil", "--online", "--out", "runs/hil"])
    _resolve_mode_flags(explicit)
    assert explicit.out == "runs/hil" and explicit.env_steps == 20000 and explicit.rounds is None
    assert explicit.bc_weight == 3.0 and explicit.lr_decay is False  # the learner's own defaults
    assert explicit.steer == "expert" and explicit.offline_ratio == 0.5 and explicit.corrector_noise == 0.0
    assert explicit.no_explore is False  # the policy samples its Gaussian unless told
    assert explicit.action_labels is False  # only a takeover's actions are imitated unless told
    # the scripted corrector's, in either mode
    assert (explicit.patience, explicit.hold_steps, explicit.grace_steps) == (8, 25, 20)
    default = parser.parse_args(["hil"])
    _resolve_mode_flags(default)
    assert default.out == "runs/hil" and default.rounds == 3 and default.bag == [str(PROJECT_BAG)]
    assert parser.parse_args(["hil", "--online"]).out is None  # resolved to runs/hil-online by mode
    online = parser.parse_args(["hil", "--online"])
    _resolve_mode_flags(online)
    assert online.out == "runs/hil-online"


def test_the_online_stage_takes_the_correctors_patience_hold_and_grace(tiny, tmp_path):
    """--patience, --hold-steps and --grace-steps reach the online stage's scripted corrector:
    one that waits longer than an episode never takes over; one that holds for a whole episode
    takes over at most once in it; one that judges no state of an episode never takes over."""
    def stage(name, *flags):
        out = tmp_path / name
        assert cli.main(["hil", "--online", "--in-process", "--no-prior", "--bag", str(tiny["bag"]), "--env-steps",
                         "200", "--publish-every", "25", "--eval-every", "100", "--eval-episodes", "1",
                         "--logger", "none", "--out", str(out), *flags]) == 0
        summary = json.loads((out / "summary.json").read_text())
        return summary["config"], summary["counts"]

    config, never = stage("patient", "--patience", "1000")
    assert config["patience"] == 1000 and never["human"] == never["takeovers"] == 0
    config, held = stage("holding", "--patience", "2", "--hold-steps", "100")
    assert config["hold_steps"] == 100 and 0 < held["takeovers"] <= held["episodes"] == 2 and held["human"] > 0
    config, unjudged = stage("graceful", "--patience", "2", "--grace-steps", "1000")
    assert config["grace_steps"] == 1000 and unjudged["human"] == unjudged["takeovers"] == 0


def test_bad_actor_counts_are_one_line_before_anything_starts(capsys, tmp_path):
    out = tmp_path / "online"
    for argv, words in (
            (["--actors", "0"], ("--actors must be in [1, 16], got 0",)),
            (["--actors", "2", "--in-process"], ("--actors 2 with --in-process",)),
            (["--actors", "3", "--env-steps", "1000"], ("--env-steps is the total over the actors",
                                                        "a multiple of 300", "got 1000"))):
        assert cli.main(["hil", "--online", "--no-prior", "--out", str(out), *argv]) == 2, argv
        _one_error_line(capsys, *words)
        assert not out.exists()
    assert cli.main(["hil", "--actors", "2"]) == 2
    _one_error_line(capsys, "--actors: only with --online")


def test_bag_repair_leaves_a_healthy_bag_alone(tmp_path, capsys):
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    String = store.types["std_msgs/msg/String"]
    with Writer(tmp_path / "chatter", version=8) as writer:  # another tool's bag: its own metadata spelling
        conn = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        for i in range(3):
            writer.write(conn, 1000 + i, store.serialize_cdr(String(data="hi"), "std_msgs/msg/String"))
    metadata = tmp_path / "chatter" / "metadata.yaml"
    before = metadata.read_bytes()
    assert cli.main(["bag", "repair", str(tmp_path / "chatter")]) == 0
    assert capsys.readouterr().out.strip().endswith("nothing to repair")
    assert metadata.read_bytes() == before


def test_help_texts_match_what_the_commands_take(capsys):
    for argv in (["eval", "--help"], ["export-onnx", "--help"], ["--help"]):
        with pytest.raises(SystemExit):
            cli.main(argv)
    out = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    assert "95 % Wilson" in out and "%%" not in out
    assert out.count("a directory holding policy.pt") == 2  # eval's and export-onnx's --checkpoint
    assert "SAC" in out and "auto" in out  # the top-level summary of train
