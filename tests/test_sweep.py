"""`offline-rl sweep` on local worker processes: the spec's checks (one line, exit 2, before
any run), the runs a grid and variants give, failures that stop no other run, resume, and
the results (Wilson per run, Newcombe against the baseline)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from offline_rl_core.commands.cli import main
from offline_rl_core.common.errors import RunFailed
from offline_rl_core.evaluation.stats import newcombe_diff_ci
from offline_rl_core.runs.parallel import run_jobs
from offline_rl_core.runs.sweep import load_sweep_spec

REPO = Path(__file__).resolve().parents[1]
MIX = REPO / "bags" / "mix.db3"
TINY = "train: {steps: 40, hidden: 16, batch_size: 16, deterministic: true, log_every: 20}\neval: {episodes: 2}\n"


def write_spec(tmp_path: Path, text: str, name: str = "spec.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def refused(capsys, spec: Path, *words: str, extra=()) -> None:
    out = spec.parent / "out"
    assert main(["sweep", str(spec), "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("offline-rl: error: "), err
    for word in words:
        assert word in err, err
    assert not out.exists()  # refused before anything was written or started


@pytest.mark.parametrize("body,words", [
    ("bags: {bags}\ngrd: {{beta: [1]}}\n", ["unknown field 'grd'", "grid"]),
    ("bags: {bags}\ngrid: {{betta: [1.0]}}\n", ["unknown field 'grid.betta'", "beta"]),
    ("bags: {bags}\nvariants: [{{algo: bc}}, {{algo: awc}}]\n", ["variants[1].algo", "unknown learner 'awc'", "iql"]),
    ("bags: {bags}\ngrid: {{beta: []}}\n", ["grid.beta", "empty list"]),
    ("bags: {bags}\nvariants: []\n", ["variants", "empty list"]),
    ("bags: [{bags}, {missing}]\n", ["field bags", "missing.db3", "no such file"]),
    ("bags: {{mix: {bags}, day2: '{glob}'}}\n", ["field bags.day2", "matches no file"]),
    ("seeds: [0]\n", ["field bags is missing"]),
    ("bags: {bags}\ngrid: {{beta: [-1.0]}}\n", ["grid.beta", "must be finite and > 0"]),
    ("bags: {bags}\ntrain: {{steps: many}}\n", ["train.steps", "expected int"]),
    ("bags: {bags}\nbaseline: bcc\n", ["field baseline", "no arm 'bcc'", "awac"]),
    ("bags: {bags}\nvariants: [{{algo: bc}}, {{algo: bc}}]\n", ["the arm 'bc' twice"]),
    ("bags: {bags}\neval: {{episodes: 0}}\n", ["eval.episodes"]),
])
def test_a_bad_spec_is_one_line_naming_the_field(tmp_path, capsys, body, words):
    spec = write_spec(tmp_path, body.format(bags=MIX, missing=tmp_path / "missing.db3", glob=tmp_path / "day2*.db3"))
    refused(capsys, spec, str(spec), *words)


def test_a_spec_that_is_not_yaml_or_not_there(tmp_path, capsys):
    refused(capsys, tmp_path / "none.yaml", "none.yaml: no such spec file")
    refused(capsys, write_spec(tmp_path, "bags: [unclosed\n"), "not valid YAML")


def test_flags_that_do_not_go_together(tmp_path, capsys):
    spec = write_spec(tmp_path, f"bags: {MIX}\n")
    refused(capsys, spec, "--address", "--engine ray", extra=["--engine", "local", "--address", "auto"])
    refused(capsys, spec, "--workers is for --engine local", extra=["--engine", "ray", "--workers", "2"])


def test_the_grid_and_variants_give_every_run_once(tmp_path):
    spec = load_sweep_spec(write_spec(tmp_path, f"""
bags: {{mix: {MIX}, again: {MIX}}}
seeds: [0, 3]
train: {{steps: 100}}
grid: {{lr: [0.0003, 0.001]}}
variants:
  - {{algo: bc}}
  - {{algo: awac, beta: [0.3, 1.0]}}
baseline: bc lr=0.0003
"""))
    assert spec.name == "spec" and list(spec.bag_sets) == ["mix", "again"]
    assert spec.arms == ["bc lr=0.0003", "bc lr=0.001", "awac lr=0.0003 beta=0.3", "awac lr=0.0003 beta=1",
                         "awac lr=0.001 beta=0.3", "awac lr=0.001 beta=1"]
    assert len(spec.runs) == 6 * 2 * 2 and len({r.name for r in spec.runs}) == len(spec.runs)
    run = next(r for r in spec.runs if r.arm == "awac lr=0.001 beta=1" and r.bag_set == "again" and r.seed == 3)
    assert run.name == "awac-lr=0.001-beta=1@again-s3"
    assert run.config["steps"] == 100 and run.config["lr"] == 0.001 and run.config["beta"] == 1.0
    assert run.params == {"lr": 0.001, "beta": 1.0} and run.bags == (str(MIX),)
    assert run.eval_episodes == 100 and run.eval_seed == 500000  # the defaults: offline-rl train's


def test_bag_paths_are_relative_to_the_spec_and_globs_expand(tmp_path):
    day = tmp_path / "fleet"
    day.mkdir()
    for name in ("b.db3", "a.db3"):
        (day / name).write_bytes(MIX.read_bytes())
    spec = load_sweep_spec(write_spec(tmp_path, "bags: {day: 'fleet/*.db3', folder: fleet}\n"))
    assert spec.bag_sets["day"] == spec.bag_sets["folder"] == (str(day / "a.db3"), str(day / "b.db3"))


def small_sweep(tmp_path: Path, bad_bag: bool = False) -> Path:
    bags = f"{{mix: {MIX}" + (f", broken: {tmp_path / 'broken.db3'}" if bad_bag else "") + "}"
    if bad_bag:
        (tmp_path / "broken.db3").write_text("this is not a bag\n")  # there, so the spec passes; fails to decode
    return write_spec(tmp_path, f"name: small\nbags: {bags}\nseeds: [0]\nvariants: [{{algo: bc}}, {{algo: awac}}]\n"
                                f"baseline: bc\n{TINY}")


@pytest.mark.slow
def test_a_failing_run_stops_no_other_and_resume_runs_only_the_unfinished(tmp_path, capsys):
    spec = small_sweep(tmp_path, bad_bag=True)
    out = tmp_path / "out"
    assert main(["sweep", str(spec), "--out", str(out), "--workers", "2"]) == RunFailed.exit_code
    captured = capsys.readouterr()
    assert "failed: bc@broken-s0: " in captured.out and "broken.db3" in captured.out
    assert "2 of 4 runs failed" in captured.err
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert [r["name"] for r in rows] == ["bc@mix-s0", "awac@mix-s0", "bc@broken-s0", "awac@broken-s0"]
    assert [r["status"] for r in rows] == ["ok", "ok", "failed", "failed"]
    assert "broken.db3" in rows[2]["error"] and rows[0]["error"] is None
    bc, awac = rows[0], rows[1]
    lo, hi = newcombe_diff_ci(awac["successes"], awac["episodes"], bc["successes"], bc["episodes"])
    assert (awac["diff_ci_lo"], awac["diff_ci_hi"]) == (round(lo, 6), round(hi, 6)) and awac["baseline"] == "bc@mix-s0"
    metrics = json.loads((out / "awac@mix-s0" / "metrics.json").read_text())
    assert awac["successes"] == metrics["eval"]["successes"] and metrics["algorithm"] == "awac"
    assert (out / "summary.md").read_text().count("FAILED") == 2 and (out / "summary.png").stat().st_size > 1000

    # without --resume the sweep's folder is not written over
    assert main(["sweep", str(spec), "--out", str(out)]) == 2
    assert "--resume continues it" in capsys.readouterr().err
    # the bag is mended: --resume runs the two failed runs and leaves the finished ones be
    (tmp_path / "broken.db3").write_bytes(MIX.read_bytes())
    finished = {n: (out / n / "metrics.json").stat().st_mtime_ns for n in ("bc@mix-s0", "awac@mix-s0")}
    assert main(["sweep", str(spec), "--out", str(out), "--resume", "--workers", "1"]) == 0
    assert "2 finished already; 2 on this machine" in capsys.readouterr().out
    assert {n: (out / n / "metrics.json").stat().st_mtime_ns for n in finished} == finished
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert [r["status"] for r in rows] == ["ok"] * 4 and len(rows) == 4
    # the same bag content under another name trains the same bytes
    assert (out / "bc@broken-s0" / "metrics.json").read_text().replace("broken.db3", "mix.db3").replace(
        str(tmp_path), str(MIX.parent)) == (out / "bc@mix-s0" / "metrics.json").read_text()

    # a changed spec does not resume over runs made with the old one
    spec.write_text(spec.read_text().replace("steps: 40", "steps: 60"))
    assert main(["sweep", str(spec), "--out", str(out), "--resume"]) == 2
    assert "config.steps: 40 there, 60 in the spec" in capsys.readouterr().err


class _Job:
    """A job of run_jobs that returns its label, or kills its own worker."""

    def __init__(self, label: str, die: bool = False):
        self.label, self.die = label, die

    def train(self, progress=None, threads_now=None):
        if self.die:
            os.kill(os.getpid(), signal.SIGKILL)
        return self.label


def test_keep_going_a_dead_worker_fails_its_job_alone():
    jobs = [_Job("a"), _Job("dies", die=True), _Job("b"), _Job("c")]
    seen = []
    results = run_jobs(jobs, 2, on_done=lambda i, r: seen.append(i), keep_going=True)
    assert [results[0], results[2], results[3]] == ["a", "b", "c"]
    assert isinstance(results[1], RunFailed) and "'dies' died (killed by signal 9" in str(results[1])
    assert sorted(seen) == [0, 1, 2, 3]


def test_without_ray_the_ray_engine_says_how_to_install_it(tmp_path):
    spec = write_spec(tmp_path, f"bags: {MIX}\n{TINY}")
    code = ("import sys; sys.modules['ray'] = None\n"  # as where Ray is not installed
            "from offline_rl_core.commands.cli import main\n"
            f"sys.exit(main(['sweep', {str(spec)!r}, '--engine', 'ray', '--out', {str(tmp_path / 'out')!r}]))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "Ray is not installed" in proc.stderr and ".[ray]" in proc.stderr


def test_the_shipped_example_spec_is_a_valid_sweep():
    spec = load_sweep_spec(REPO / "bags" / "sweep.yaml")
    assert spec.baseline == "bc" and len(spec.runs) == 15
    assert spec.arms == ["bc", "filtered_bc filter_by=goal", "awac beta=0.3", "awac beta=1", "iql"]
    assert {r.bags for r in spec.runs} == {(str(MIX),)}
