"""The hand-written MLP forward/backward must be the plain autograd MLP's maths."""

import pytest
import torch

from offline_rl_core.fast.kernel_choice import Kernels, native_bf16, onednn_linear_available
from offline_rl_core.learners.networks import EnsembleMLP

BACKENDS = ["blas"] + (["onednn"] if onednn_linear_available() else [])


def _autograd_reference(net: EnsembleMLP, x: torch.Tensor) -> torch.Tensor:
    h = x
    for i, (w, b) in enumerate(zip(net.weights, net.biases)):
        h = torch.baddbmm(b, h, w)
        if i < len(net.weights) - 1:
            h = torch.relu(h)
    return torch.tanh(h) if net.tanh_output else h


def _outputs_and_grads(net, fn, x, grad_out):
    net.zero_grad(set_to_none=True)
    x = x.detach().clone().requires_grad_(True)
    y = fn(x)
    (y * grad_out).sum().backward()
    return [y.detach()] + [p.grad for p in net.parameters()] + [x.grad]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("members,tanh_output,out_dim", [(1, True, 2), (2, False, 1), (3, True, 3)])
def test_fp32_forward_and_gradients_match_autograd(members, tanh_output, out_dim, backend):
    torch.manual_seed(0)
    net = EnsembleMLP(members, 7, 32, out_dim, tanh_output=tanh_output, kernels=Kernels("fp32", backend, backend, backend))
    x, grad_out = torch.randn(members, 19, 7), torch.randn(members, 19, out_dim)
    ours = _outputs_and_grads(net, net, x, grad_out)
    ref = _outputs_and_grads(net, lambda t: _autograd_reference(net, t), x, grad_out)
    for a, b in zip(ours, ref):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_members_do_not_depend_on_each_other():
    torch.manual_seed(1)
    net = EnsembleMLP(2, 5, 16, 1)
    x = torch.randn(2, 9, 5)
    y = net(x)
    x2 = x.clone()
    x2[1] += 1.0  # change member 1's input only
    assert torch.equal(net(x2)[0], y[0])


@pytest.mark.skipif(not native_bf16(), reason="no native bf16 on this CPU")
@pytest.mark.parametrize("backend", BACKENDS)
def test_bf16_hidden_layer_is_within_bf16_rounding(backend):
    torch.manual_seed(2)
    net = EnsembleMLP(2, 10, 256, 1, kernels=Kernels("bf16", backend, backend, backend))
    x, grad_out = torch.randn(2, 256, 10), torch.randn(2, 256, 1)
    ours = _outputs_and_grads(net, net, x, grad_out)
    ref = _outputs_and_grads(net, lambda t: _autograd_reference(net, t), x, grad_out)
    for a, b in zip(ours, ref):
        assert float((a - b).norm() / b.norm()) < 0.05  # bf16 has 8 mantissa bits


def test_kernel_choice_is_measured_once_and_reused(tmp_path, monkeypatch):
    """The choice is cached per machine, so a second process makes the same one (and a
    seed stays bit-reproducible) without measuring again."""
    import json
    import subprocess
    import sys

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.delenv("PUSHER_RL_KERNELS", raising=False)
    code = "from offline_rl_core.fast.kernel_choice import choose; print(choose(True, 32, 16).describe())"
    first = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    cache = tmp_path / "pusher-rl" / "kernels.json"
    entries = json.loads(cache.read_text())
    assert len(entries) == 1
    (entry,) = entries.values()
    assert entry["dtype"] == "fp32" and set(entry["totals_us"]) == {"fp32"}  # deterministic: fp32 only
    entry["forward"] = "blas" if entry["forward"] == "onednn" else entry["forward"]  # a choice only the cache knows
    cache.write_text(json.dumps({k: entry for k in entries}))
    second = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert second.startswith(f"fp32 (forward {entry['forward']},"), (first, second)


def test_forced_kernels_are_checked(monkeypatch):
    from offline_rl_core.common.errors import UserError
    from offline_rl_core.fast.kernel_choice import choose

    monkeypatch.setenv("PUSHER_RL_KERNELS", "fp16")
    with pytest.raises(UserError, match="PUSHER_RL_KERNELS=fp16: expected fp32 or bf16"):
        choose(True)
    monkeypatch.setenv("PUSHER_RL_KERNELS", "bf16")
    with pytest.raises(UserError, match="contradicts --deterministic"):
        choose(True)
    monkeypatch.setenv("PUSHER_RL_KERNELS", "fp32-blas")
    assert choose(False) == Kernels("fp32", "blas", "blas", "blas")


@pytest.mark.skipif(not native_bf16(), reason="no native bf16 on this CPU")
def test_bf16_training_ends_where_fp32_does(monkeypatch):
    """bf16 kernels must train: the same BC run in fp32 and in bf16 ends at about the same
    loss. (Guards against a stale bf16 copy of weights the optimiser has since updated,
    which an earlier autocast version served: it ended at 0.926 against fp32's 0.288.)"""
    from offline_rl_core.data.collect import collect_transitions
    from offline_rl_core.learners import TrainConfig, train_seeds

    data = collect_transitions(10, 0.3, 0)
    cfg = dict(algo="bc", steps=400, batch_size=64, hidden=32, log_every=100)
    fp32 = train_seeds(data, TrainConfig(**cfg, deterministic=True), [0])[0]
    monkeypatch.setenv("PUSHER_RL_KERNELS", "bf16")
    bf16 = train_seeds(data, TrainConfig(**cfg, deterministic=False), [0])[0]
    assert "bf16" in bf16.checkpoint["kernels"] and "fp32" in fp32.checkpoint["kernels"]
    mse = lambda r: float(((r.policy.act(data.obs) - data.action) ** 2).mean())  # noqa: E731
    assert abs(mse(bf16) - mse(fp32)) < 0.05 * mse(fp32) + 0.005
