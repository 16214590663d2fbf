"""Training on an NVIDIA GPU (`--device cuda`): the same maths as the CPU, the CUDA
graph the same as eager steps, checkpoints that load anywhere.

CI has no GPU: these run where CUDA is present and are skipped elsewhere, except the
error a user gets when asking for a GPU that is not there.
"""

import subprocess
import sys

import numpy as np
import pytest
import torch

from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.learners import TrainConfig, train_seeds

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU here")


@pytest.fixture(scope="module")
def data():
    return collect_transitions(20, 0.3, 0)


def _weights(result) -> np.ndarray:
    return np.concatenate([v.numpy().ravel() for _, v in sorted(result.checkpoint["policy_state"].items())])


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_asking_for_a_missing_gpu_is_a_one_line_error(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "offline_rl_core", "train", "--bag", "bags/mix.db3", "--device", "cuda",
                           "--out", str(tmp_path / "run")], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "device cuda: no CUDA GPU is available" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "run").exists()


@cuda
@pytest.mark.parametrize("algo", ["awac", "bc", "iql", "naive"])
def test_cuda_graph_replays_the_eager_step(data, algo):
    """Two seeds, long enough to pass the warm-up and replay the graph many times."""
    cfg = dict(algo=algo, steps=60, log_every=20, device="cuda", deterministic=True)
    eager = train_seeds(data, TrainConfig(cuda_graph=False, **cfg), [0, 1])
    graph = train_seeds(data, TrainConfig(cuda_graph=True, **cfg), [0, 1])
    for e, g in zip(eager, graph):
        np.testing.assert_allclose(_weights(g), _weights(e), rtol=0, atol=1e-6)
        for key in e.history:
            np.testing.assert_allclose(g.history[key], e.history[key], rtol=1e-5, atol=1e-6)
        if e.mean_abs_q is not None:
            assert g.mean_abs_q == pytest.approx(e.mean_abs_q, rel=1e-5)


@cuda
def test_gpu_training_follows_the_cpu(data):
    """Same init and batches on both devices: after a few steps fp32 weights agree to
    float rounding (cuBLAS and oneDNN sum in different orders)."""
    cfg = dict(algo="awac", steps=10, log_every=5, deterministic=True)
    cpu = train_seeds(data, TrainConfig(**cfg), [3])[0]
    gpu = train_seeds(data, TrainConfig(device="cuda", **cfg), [3])[0]
    np.testing.assert_allclose(_weights(gpu), _weights(cpu), rtol=0, atol=1e-4)


@cuda
def test_a_gpu_checkpoint_serves_on_the_cpu(data, tmp_path):
    from offline_rl_core.serving.checkpoint import save_checkpoint
    from offline_rl_core.serving.policy import load_policy

    result = train_seeds(data, TrainConfig(algo="bc", steps=20, log_every=10, device="cuda"), [0])[0]
    assert all(v.device.type == "cpu" for v in result.checkpoint["policy_state"].values())
    save_checkpoint(tmp_path / "policy.pt", result.checkpoint)
    policy = load_policy(tmp_path / "policy.pt")
    action = policy.act(data.obs[:4])
    assert np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0)
