"""bench/RESULTS.md is generated (bench/results_page.py): the committed page is exactly what the
committed JSON gives, so nobody edits it by hand, and every JSON file under bench/ names the
command that measured its figures and the machine (CPU model and flags) it ran on."""

from __future__ import annotations

import copy
import json
import sys
from pathlib import Path

import pytest
from bench_scripts import bench_script

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "bench"


@pytest.fixture(scope="module")
def page():
    return bench_script("results_page")


def test_the_committed_page_is_what_the_committed_json_gives(page):
    assert (BENCH / "RESULTS.md").read_text() == page.render(page.load()), \
        "bench/RESULTS.md differs from what bench/*.json give: run python bench/results_page.py (never edit it by hand)"


def runs_of(payload: dict) -> list[dict]:
    """The parts of a file that each name a command and a machine: the file, or each of its runs."""
    return list(payload["runs"].values()) if isinstance(payload.get("runs"), dict) else [payload]


@pytest.mark.parametrize("path", sorted(BENCH.glob("*.json")), ids=lambda p: p.name)
def test_every_bench_json_names_its_command_and_machine(path):
    for run in runs_of(json.loads(path.read_text())):
        commands = [run["command"]] if run.get("command") else run.get("commands") or []
        assert commands and all(isinstance(c, str) and c.strip() for c in commands), f"{path.name}: no command"
        machine = run.get("machine") or {}
        assert machine.get("cpu_model") or machine.get("cpu"), f"{path.name}: no CPU model"
        flags = [machine.get(k) for k in ("cpu_isa_flags", "isa_flags", "isa", "cpu_flags", "bf16_flags")]
        assert any(flags), f"{path.name}: no ISA flags"


def bench_run(ours: float, measured_at: str, name: str = "awac_steps_per_s_default_vs_chapter") -> dict:
    figure = {"ours": ours, "reference": 100.0, "reference_name": "chapter loop", "ratio": ours / 100.0,
              "unit": "steps/s", "higher_is_better": True, "target_text": ">= 3x", "met": ours >= 300, "status": "ok",
              "note": "", "extra": {}}
    return {"train": {name: figure}, "settings": {"device": "cpu", "quick": False}, "measured_at": measured_at,
            "command": "offline-rl bench --only train --json bench/x.json",
            "machine": {"cpu_model": "Test CPU", "cpu_count": 2, "isa_flags": ["avx2"]}}


def test_a_newer_run_replaces_the_figures_it_measured_again(page):
    old = bench_run(150.0, "2026-01-01T00:00:00Z")
    old["eval"] = copy.deepcopy(old["train"])  # a figure the newer run does not measure again
    files = {"results.json": old, "results_later.json": bench_run(250.0, "2026-01-02T00:00:00Z")}
    text = page.render(files)
    assert "250 steps/s" in text and "150 steps/s" in text  # the old file still holds the only eval figure
    only_train = {"results.json": bench_run(150.0, "2026-01-01T00:00:00Z"),
                  "results_later.json": bench_run(250.0, "2026-01-02T00:00:00Z")}
    text = page.render(only_train)
    assert "150 steps/s" not in text
    assert "Files with no current figure" in text and "[results.json](results.json)" in text.split("no current figure")[1]


def test_another_cpu_is_another_section(page):
    other = bench_run(150.0, "2026-01-03T00:00:00Z")
    other["machine"] = {"cpu_model": "Other CPU", "cpu_count": 2, "isa_flags": ["avx2", "avx512f"]}
    text = page.render({"a.json": bench_run(250.0, "2026-01-02T00:00:00Z"), "b.json": other})
    assert "### Test CPU, 2 cores, flags avx2" in text and "### Other CPU, 2 cores, flags avx2 avx512f" in text
    assert "150 steps/s" in text and "250 steps/s" in text


def test_a_json_file_no_section_renders_is_refused(page):
    with pytest.raises(SystemExit, match="unknown_figures.json"):
        page.render({"unknown_figures.json": {"figures": [1, 2, 3]}})


def test_bench_writes_its_command_and_time(tmp_path, monkeypatch):
    from offline_rl_core.commands.cli import main

    out = tmp_path / "bench.json"
    argv = ["bench", "--tiny", "--only", "eval", "--threads", "1", "--json", str(out)]
    monkeypatch.setattr(sys, "argv", [str(REPO / ".venv" / "bin" / "offline-rl"), *argv])  # as the console script runs
    assert main(argv) == 0
    payload = json.loads(out.read_text())
    assert payload["command"] == "offline-rl " + " ".join(argv)
    assert payload["measured_at"].endswith("Z") and payload["machine"]["cpu_model"]
