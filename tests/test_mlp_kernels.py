"""The hand-written MLP forward/backward must be the plain autograd MLP's maths."""

import pytest
import torch

from offline_rl_core.learners.precision import native_bf16
from offline_rl_core.mlp_kernels import onednn_linear_available
from offline_rl_core.networks import EnsembleMLP


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


@pytest.mark.parametrize("members,tanh_output,out_dim", [(1, True, 2), (2, False, 1), (3, True, 3)])
def test_fp32_forward_and_gradients_match_autograd(members, tanh_output, out_dim):
    torch.manual_seed(0)
    net = EnsembleMLP(members, 7, 32, out_dim, tanh_output=tanh_output)
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
def test_bf16_hidden_layer_is_within_bf16_rounding():
    torch.manual_seed(2)
    net = EnsembleMLP(2, 10, 256, 1, compute_dtype=torch.bfloat16)
    x, grad_out = torch.randn(2, 256, 10), torch.randn(2, 256, 1)
    ours = _outputs_and_grads(net, net, x, grad_out)
    ref = _outputs_and_grads(net, lambda t: _autograd_reference(net, t), x, grad_out)
    for a, b in zip(ours, ref):
        assert float((a - b).norm() / b.norm()) < 0.05  # bf16 has 8 mantissa bits


def test_onednn_detection_is_a_plain_bool():
    assert onednn_linear_available() in (True, False)
