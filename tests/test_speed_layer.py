"""The speed layer is optional: a copy of the package without ``offline_rl_core/fast`` trains
every learner with plain autograd, through the same command a user types."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]

# Run the copy, not the editable install of this checkout: drop the install's import hook.
RUN_COPY = """
import sys
sys.meta_path[:] = [f for f in sys.meta_path if not (getattr(f, "__module__", "") or "").startswith("__editable___offline_rl_core")]
sys.path.insert(0, sys.argv.pop(1))
from offline_rl_core.commands.cli import main
code = main(sys.argv[1:])
loaded = sorted(m for m in sys.modules if m.startswith("offline_rl_core"))
print("LOADED", " ".join(loaded))
print("FROM", sys.modules["offline_rl_core"].__file__)
sys.exit(code)
"""


@pytest.fixture(scope="module")
def package_without_speed_layer(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("no_fast")
    shutil.copytree(REPO / "offline_rl_core", root / "offline_rl_core",
                    ignore=shutil.ignore_patterns("fast", "__pycache__"))
    return root


@pytest.mark.parametrize("algo", ["awac", "sac"])
def test_the_learners_train_without_the_speed_layer(package_without_speed_layer, tmp_path, algo):
    out = tmp_path / algo
    run = subprocess.run([sys.executable, "-c", RUN_COPY, str(package_without_speed_layer), "train", "--bag",
                          str(REPO / "bags" / "mix.db3"), "--algo", algo, "--steps", "200", "--log-every", "50",
                          "--eval-episodes", "5", "--out", str(out)],
                         capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    loaded = next(line for line in run.stdout.splitlines() if line.startswith("LOADED")).split()[1:]
    assert "offline_rl_core.fast" not in loaded and "offline_rl_core.runs" in loaded
    assert next(line for line in run.stdout.splitlines() if line.startswith("FROM")).endswith(
        str(package_without_speed_layer / "offline_rl_core" / "__init__.py"))
    checkpoint = torch.load(out / "policy.pt", weights_only=True)
    assert checkpoint["kernels"] == "autograd" and checkpoint["train_step"] == "eager"
    assert all(bool(torch.isfinite(t).all()) for t in checkpoint["policy_state"].values())
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["steps"] == 200 and metrics["eval"]["episodes"] == 5
    losses = metrics["final_losses"]
    assert losses and all(v == v for v in losses.values())  # finite, not NaN


def test_with_the_speed_layer_the_same_command_replays_the_recorded_step(tmp_path):
    from offline_rl_core.commands.cli import main

    assert main(["train", "--bag", str(REPO / "bags" / "mix.db3"), "--algo", "awac", "--steps", "200",
                 "--eval-episodes", "0", "--out", str(tmp_path / "awac")]) == 0
    checkpoint = torch.load(tmp_path / "awac" / "policy.pt", weights_only=True)
    assert checkpoint["train_step"] in ("cpp", "python") and checkpoint["kernels"] != "autograd"
