"""The written-out training steps (Python, and C++ for AWAC) give the same bytes as
autograd: the speed-up must not change a single result."""

import shutil
import subprocess
import sys

import numpy as np
import pytest

from offline_rl_core.collect import collect_transitions
from offline_rl_core.learners import TrainConfig, train_seeds
from offline_rl_core.learners.precision import native_bf16

has_compiler = shutil.which("g++") is not None and shutil.which("ninja") is not None
PRECISIONS = [True] + ([False] if native_bf16() else [])  # deterministic (fp32), default (bf16 where native)


@pytest.fixture(scope="module")
def data():
    return collect_transitions(30, 0.3, 0)


def _run(monkeypatch, data, mode: str, algo: str, deterministic: bool, seeds):
    monkeypatch.setenv("PUSHER_RL_STEP", mode)
    cfg = TrainConfig(algo=algo, steps=60, log_every=10, deterministic=deterministic)
    return train_seeds(data, cfg, seeds)


def _assert_same_bytes(got, want):
    for g, w in zip(got, want):
        parts_g = [g.checkpoint["policy_state"], *g.checkpoint["learner_state"].values()]
        parts_w = [w.checkpoint["policy_state"], *w.checkpoint["learner_state"].values()]
        for pg, pw in zip(parts_g, parts_w):
            for key in pw:
                np.testing.assert_array_equal(pg[key].numpy(), pw[key].numpy(), err_msg=key)
        assert g.history == w.history
        assert g.mean_abs_q == w.mean_abs_q


@pytest.mark.parametrize("deterministic", PRECISIONS)
@pytest.mark.parametrize("algo", ["awac", "bc"])
def test_python_step_is_byte_identical_to_autograd(monkeypatch, data, algo, deterministic):
    want = _run(monkeypatch, data, "autograd", algo, deterministic, [0, 1])
    got = _run(monkeypatch, data, "python", algo, deterministic, [0, 1])
    _assert_same_bytes(got, want)


@pytest.mark.skipif(not has_compiler, reason="no g++ / ninja: the C++ step cannot be built here")
@pytest.mark.parametrize("deterministic", PRECISIONS)
def test_cpp_step_is_byte_identical_to_autograd(monkeypatch, data, deterministic):
    want = _run(monkeypatch, data, "autograd", "awac", deterministic, [0, 2])
    got = _run(monkeypatch, data, "cpp", "awac", deterministic, [0, 2])  # raises if it cannot be built
    _assert_same_bytes(got, want)


def test_naive_max_q_keeps_its_own_actor_loss(monkeypatch, data):
    """NaiveMaxQ subclasses AWAC with a different actor loss: the written-out AWAC step
    must not replace it."""
    from offline_rl_core.learners.naive import NaiveMaxQ

    learner = NaiveMaxQ(TrainConfig(algo="naive"), 1, [None], data.obs.shape[1], data.action.shape[1])
    assert learner._written_out is None


@pytest.mark.skipif(not has_compiler, reason="no g++ / ninja")
def test_build_command_reports_ready():
    proc = subprocess.run([sys.executable, "-m", "offline_rl_core.learners.awac_cpp"], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "C++ AWAC step ready" in proc.stdout


def test_unknown_step_mode_is_a_one_line_error(monkeypatch, tmp_path):
    monkeypatch.setenv("PUSHER_RL_STEP", "fastest")
    proc = subprocess.run([sys.executable, "-m", "offline_rl_core", "train", "--bag", "bags/mix.db3", "--steps", "5",
                           "--eval-episodes", "0", "--out", str(tmp_path / "run")], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "PUSHER_RL_STEP=fastest: expected one of auto, cpp, python, autograd" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "run").exists()


def test_a_lock_left_by_an_interrupted_build_does_not_hang_the_next_run(tmp_path):
    """torch's loader waits forever on its build lock; a Ctrl-C during the first
    compile leaves one behind. An old lock is cleared, a fresh one (a build running
    in another process) is left alone."""
    import os
    import time

    from offline_rl_core.learners.awac_cpp import _clear_stale_lock

    lock = tmp_path / "lock"
    lock.write_text("")
    _clear_stale_lock(tmp_path)
    assert lock.exists()
    old = time.time() - 3600
    os.utime(lock, (old, old))
    _clear_stale_lock(tmp_path)
    assert not lock.exists()
