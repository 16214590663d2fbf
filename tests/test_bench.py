"""The benchmark harness (`offline-rl bench`): its JSON schema on tiny settings, and the
chapter reference loop agreeing with our AWAC. No timing assertions: timings belong
to bench/RESULTS.md, not to a test on a shared machine."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from offline_rl_core.runs import chapter_loop as chapter
from offline_rl_core.benchmarks.harness import GROUPS, BenchSettings, Figure, figure, format_table, run_bench
from offline_rl_core.commands.cli import main
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.learners import TrainConfig, train_seeds

FIGURE_KEYS = {"ours", "reference", "reference_name", "ratio", "unit", "higher_is_better", "target_text", "met",
               "status", "note", "extra"}


def check_schema(payload: dict, groups) -> None:
    assert set(GROUPS) <= set(payload)
    assert {"cpu_model", "isa_flags", "kernels", "amx", "avx512_bf16", "torch_threads"} <= set(payload["machine"])
    for g in groups:
        assert payload[g], f"group {g} has no figures"
        for name, fig in payload[g].items():
            assert FIGURE_KEYS <= set(fig), (g, name)
            assert fig["status"] in ("ok", "pending", "skipped"), (g, name)
            if fig["status"] == "ok":
                assert fig["ours"] is not None and fig["reference"] is not None, (g, name)
                assert fig["reference_name"], (g, name)
                if fig["ours"] and fig["reference"]:
                    want = fig["ours"] / fig["reference"] if fig["higher_is_better"] else fig["reference"] / fig["ours"]
                    assert fig["ratio"] == pytest.approx(want, rel=1e-2, abs=1e-3), (g, name)
            else:
                assert fig["note"], f"{g}/{name} is {fig['status']} without a reason"


def test_quick_harness_tiny_writes_the_schema(tmp_path, capsys):
    out = tmp_path / "results.json"
    rc = main(["bench", "--tiny", "--only", "train,decode,eval", "--threads", "1", "--json", str(out)])
    assert rc == 0
    payload = json.loads(out.read_text())
    check_schema(payload, ["train", "decode", "eval"])
    train = payload["train"]
    assert any(k.startswith("awac_steps_per_s_deterministic_vs_chapter") for k in train)
    assert any(k.startswith("awac_steps_per_s_default_vs_chapter") for k in train)
    assert any(k.startswith("experiment_") for k in train)
    assert any("d3rlpy" in k for k in train)  # measured, or skipped with the reason
    assert "bag_decode_transitions_per_s" in payload["decode"]
    printed = capsys.readouterr().out
    assert "ratio" in printed and "wrote" in printed


def test_serve_inference_figure_tiny(tmp_path):
    from offline_rl_core.benchmarks import serve

    s = BenchSettings.tiny_settings()
    figs = serve.inference_figures(s, serve.trained_checkpoint(s), log=lambda line: None)
    assert figs[0].name == "inference_p99_ms_numpy_vs_torch"
    assert figs[0].ours > 0 and figs[0].reference > 0


@pytest.mark.slow
@pytest.mark.ros
def test_ros_groups_tiny(tmp_path):
    from offline_rl_core.benchmarks.ros_procs import ros_missing

    if ros_missing():
        pytest.skip(ros_missing())
    _, payload = run_bench(BenchSettings.tiny_settings(), ["serve", "record"], log=lambda line: None)
    check_schema(payload, ["serve", "record"])


def test_figure_ratio_and_table():
    rate = figure("train", "x", "steps/s", 300.0, 100.0, "ref", target=lambda o, r, x: x >= 3, target_text=">= 3x")
    assert rate.ratio == pytest.approx(3.0) and rate.met is True
    latency = figure("serve", "y", "ms", 0.05, 0.2, "ref", higher_is_better=False, target=lambda o, r, x: o < 0.1)
    assert latency.ratio == pytest.approx(4.0) and latency.met is True
    missing = Figure("serve", "z", "ms", None, None, "echo", status="pending", note="nodes not built")
    assert missing.ratio is None and missing.to_dict()["ratio"] is None
    table = format_table([rate, latency, missing])
    assert "3.00x" in table and "pending" in table


def test_bench_rejects_unknown_group(capsys):
    assert main(["bench", "--only", "train,nope"]) != 0
    assert "nope" in capsys.readouterr().err


def test_chapter_awac_and_ours_agree_in_distribution():
    """Same data, sizes and hyper-parameters: the chapter's plain loop and our ensemble
    AWAC draw different random streams, so they agree in distribution, not bit for bit.
    Over three seeds each, the critics' mean Q on the logged (s, a) and the policy's
    regression error must land together."""
    torch.set_num_threads(1)
    data = collect_transitions(10, 0.3, 0)
    tensors = chapter.dataset_tensors(data)
    settings = chapter.ChapterSettings(steps=300, batch_size=64, hidden=32)
    obs, act = tensors["obs"], tensors["action"]
    seeds = [0, 1, 2]
    ch_q, ch_mse = [], []
    for seed in seeds:
        torch.manual_seed(seed)
        pol, q1, q2, _ = chapter.train_awac_with_critics(tensors, settings)
        with torch.no_grad():
            ch_q.append(float((0.5 * (q1(obs, act) + q2(obs, act))).mean()))
            ch_mse.append(float((pol(obs) - act).pow(2).mean()))
    ours = train_seeds(data, TrainConfig(algo="awac", steps=300, batch_size=64, hidden=32), seeds)
    our_q = [-r.mean_abs_q for r in ours]  # rewards are -dist: Q is negative here
    our_mse = [float(((r.policy.act(data.obs) - data.action) ** 2).mean()) for r in ours]
    assert all(q < 0 for q in ch_q)
    spread = np.std(ch_q + our_q) + 0.05
    assert abs(np.mean(ch_q) - np.mean(our_q)) < 3 * spread, (ch_q, our_q)
    assert abs(np.mean(ch_mse) - np.mean(our_mse)) < 0.02, (ch_mse, our_mse)


def test_chapter_bc_and_ours_agree_in_distribution():
    torch.set_num_threads(1)
    data = collect_transitions(10, 0.3, 0)
    tensors = chapter.dataset_tensors(data)
    settings = chapter.ChapterSettings(steps=300, batch_size=64, hidden=32)
    ch = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        pol = chapter.train_bc(tensors, settings)
        with torch.no_grad():
            ch.append(float((pol(tensors["obs"]) - tensors["action"]).pow(2).mean()))
    ours = train_seeds(data, TrainConfig(algo="bc", steps=300, batch_size=64, hidden=32), [0, 1])
    our = [float(((r.policy.act(data.obs) - data.action) ** 2).mean()) for r in ours]
    assert abs(np.mean(ch) - np.mean(our)) < 0.02, (ch, our)


def test_isa_avx2_caps_every_kernel_and_says_so(tmp_path):
    """`--isa avx2` runs the bench as on an AVX2-only CPU: torch, oneDNN and MKL capped,
    the cap and the CPU's own flags both in the JSON beside the figures."""
    import subprocess
    import sys

    out = tmp_path / "avx2.json"
    run = subprocess.run([sys.executable, "-m", "offline_rl_core.commands.cli", "bench", "--tiny", "--only", "decode",
                          "--isa", "avx2", "--json", str(out)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    machine = json.loads(out.read_text())["machine"]
    assert machine["kernel_isa_limits"] == {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2",
                                            "MKL_ENABLE_INSTRUCTIONS": "AVX2"}
    assert not any(f.startswith(("avx512", "amx")) for f in machine["isa_flags"])
    assert machine["native_bf16"] is False
    assert "capping the kernels at AVX2" in run.stdout


def test_kernel_choice_is_cached_apart_under_an_isa_cap(monkeypatch):
    """A choice measured with AVX-512 kernels is not reused when the kernels are capped."""
    from offline_rl_core.common import machine

    uncapped = machine.machine_key("256x256")
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    assert machine.machine_key("256x256") != uncapped
