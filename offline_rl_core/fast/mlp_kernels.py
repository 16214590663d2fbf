"""The ensemble MLP's forward and backward, written by hand for speed on CPU.

``in -> relu(256) -> relu(256) -> out`` per member. Almost all of a training step's
arithmetic is the 256x256 hidden layer, so that is the layer this module is about: its
three products run on the kernels ``kernel_choice`` measured fastest on this CPU (oneDNN
or the default BLAS, fp32 or bf16). In bf16 the input and output layers stay fp32: they
cost almost nothing, and bf16 Q values (8 mantissa bits) would quantise AWAC's advantage
weights. Members are multiplied one by one (which also keeps each member's numbers
independent of how many members train beside it).

``mlp_forward`` and ``mlp_backward`` are the whole network, forward and backward; the
autograd ``Function`` below wraps them, so a network call is one autograd node instead
of one per op. They are the maths of ``learners.networks.EnsembleMLP`` derived by hand, so
they are used for a network only where ``covers`` and ``disagreement_with_autograd`` say
they compute what its own autograd forward does (``fast.FastPath.network_forward``).
"""

from __future__ import annotations

import torch

import functools

from .kernel_choice import Kernels, product

_relu_grad = torch.ops.aten.threshold_backward


class HiddenLayer:
    """The hidden layer's three products for one member (2-D tensors), on the chosen
    kernels; ``cast`` brings an fp32 tensor to their dtype."""

    def __init__(self, kernels: Kernels | None = None):
        self.kernels = kernels or Kernels()
        self.dtype = self.kernels.torch_dtype
        self.forward_relu = product("forward", self.kernels.forward)  # relu(x @ w + b)
        self.grad_weight = product("grad_weight", self.kernels.grad_weight)  # x.T @ g
        self.grad_input = product("grad_input", self.kernels.grad_input)  # g @ w.T

    def cast(self, t: torch.Tensor) -> torch.Tensor:
        return t.to(self.dtype)


def mlp_forward(x, w1, b1, w2, b2, w3, b3, tanh_output: bool, hidden: HiddenLayer):
    """(E, B, in) -> (y, w2c, activations): the three layers member by member; ``w2c`` is
    the hidden weight in the hidden layer's precision."""
    members = w1.shape[0]
    w2c, b2c = hidden.cast(w2), hidden.cast(b2)
    acts, outs = [], []
    for m in range(members):
        h1 = torch.addmm(b1[m], x[m], w1[m]).relu_()
        h1c = hidden.cast(h1)
        h2 = hidden.forward_relu(h1c, w2c[m], b2c[m, 0]).float()
        # the thin output layer as (w.T @ h.T).T: MKL is much slower on a 256x256 by
        # 256x2 product than on its transpose on some CPUs
        outs.append(torch.addmm(b3[m].t(), w3[m].t(), h2.t()).t())
        acts.append((h1, h1c, h2))
    y = _stacked(outs).contiguous()
    if tanh_output:
        y.tanh_()
    return y, w2c, acts


def _stacked(parts: list[torch.Tensor]) -> torch.Tensor:
    """The members' results on a leading member axis: one member's as a view (no copy)."""
    return parts[0].unsqueeze(0) if len(parts) == 1 else torch.stack(parts)


def mlp_backward(grad_y, x, w1, w2c, w3, y, acts, tanh_output: bool, hidden: HiddenLayer, input_grad: bool,
                 weight_grads: bool = True):
    """Gradients (x or None, w1, b1, w2, b2, w3, b3) of ``mlp_forward``'s output; the
    weights' are None without ``weight_grads`` (a loss that moves another network
    through this one's output, as an actor's through a critic, needs only x's)."""
    g3_all = grad_y * (1.0 - y * y) if tanh_output else grad_y
    grads = [None] * 6
    grad_w2_parts = []
    if weight_grads:
        grad_w1, grad_w3 = torch.empty_like(w1), torch.empty_like(w3)
        grad_b1 = x.new_empty(w1.shape[0], 1, w1.shape[2])
        grad_b2 = x.new_empty(w2c.shape[0], 1, w2c.shape[2])
        grad_b3 = g3_all.sum(1, keepdim=True)
    grad_x = torch.empty_like(x) if input_grad else None
    for m in range(w1.shape[0]):
        h1, h1c, h2 = acts[m]
        g3 = g3_all[m]
        if weight_grads:
            grad_w3[m].copy_(g3.t().mm(h2).t())
        g2 = _relu_grad(g3.mm(w3[m].t()), h2, 0)
        g2c = hidden.cast(g2)
        if weight_grads:
            torch.sum(g2, 0, keepdim=True, out=grad_b2[m])
            grad_w2_parts.append(hidden.grad_weight(h1c, g2c).float())  # fp32, like the parameter
        g1 = _relu_grad(hidden.grad_input(g2c, w2c[m]).float(), h1, 0)
        if weight_grads:
            torch.mm(x[m].t(), g1, out=grad_w1[m])
            torch.sum(g1, 0, keepdim=True, out=grad_b1[m])
        if grad_x is not None:
            torch.mm(g1, w1[m].t(), out=grad_x[m])
    if weight_grads:
        grads = [grad_w1, grad_b1, _stacked(grad_w2_parts), grad_b2, grad_w3, grad_b3]
    return (grad_x, *grads)


class _EnsembleMLPFunction(torch.autograd.Function):
    """Members one by one with 2-D products: torch's batched ``bmm`` on CPU is much
    slower than ``addmm`` for the thin first and last layers."""

    @staticmethod
    def forward(ctx, x, w1, b1, w2, b2, w3, b3, tanh_output: bool, hidden: HiddenLayer):
        y, w2c, acts = mlp_forward(x, w1, b1, w2, b2, w3, b3, tanh_output, hidden)
        ctx.tanh_output, ctx.hidden = tanh_output, hidden
        ctx.save_for_backward(x, w1, w2c, w3, y, *[t for act in acts for t in act])
        return y

    @staticmethod
    def backward(ctx, grad_y):
        x, w1, w2c, w3, y, *flat = ctx.saved_tensors
        acts = [tuple(flat[i: i + 3]) for i in range(0, len(flat), 3)]
        grads = mlp_backward(grad_y, x, w1, w2c, w3, y, acts, ctx.tanh_output, ctx.hidden, ctx.needs_input_grad[0],
                             weight_grads=any(ctx.needs_input_grad[1:7]))
        return (*grads, None, None)


def ensemble_mlp(x, weights, biases, tanh_output: bool, hidden: HiddenLayer) -> torch.Tensor:
    """(E, B, in) -> (E, B, out) for a three-layer ensemble MLP."""
    (w1, w2, w3), (b1, b2, b3) = weights, biases
    return _EnsembleMLPFunction.apply(x, w1, b1, w2, b2, w3, b3, tanh_output, hidden)


def covers(net) -> bool:
    """Whether ``net`` has the shape these kernels are written for: three layers, the
    middle one square (in -> hidden -> hidden -> out)."""
    w = list(net.weights)
    return len(w) == 3 and w[1].shape[1] == w[1].shape[2] == w[0].shape[2] and w[2].shape[1] == w[1].shape[2]


# How far the hand-written kernels may be from autograd: fp32 reorders a few sums. A bf16
# hidden layer keeps 8 mantissa bits, and its ReLU takes the sign of the rounded
# pre-activation: the few units within rounding of zero switch off where fp32's are on, each
# taking its whole share of the gradient, so the first layers' gradients differ by about
# sqrt(share switched) (0.03-0.09 measured on 5 random rows, AMD EPYC avx512_bf16). A wrong
# kernel (a transpose, a missing term) is off by the order of the gradient itself.
_TOLERANCE = {"fp32": 1e-4, "bf16": 0.2}


def disagreement_with_autograd(net, hidden: HiddenLayer) -> str | None:
    """None when ``mlp_forward``/``mlp_backward`` give ``net``'s own autograd outputs and
    gradients (within rounding) on random inputs of its shape; otherwise what differs.
    Checked once per shape, kernels and output squashing in a process."""
    return _disagreement(net.__class__, net.in_dim, net.hidden, net.out_dim, net.tanh_output, hidden.kernels)


@functools.lru_cache(maxsize=None)
def _disagreement(cls, in_dim: int, width: int, out_dim: int, tanh_output: bool, kernels: Kernels) -> str | None:
    gen = torch.Generator().manual_seed(0)  # its own stream: the run's random numbers are untouched
    probe = cls(2, in_dim, width, out_dim, [gen, gen], tanh_output=tanh_output)
    x = torch.randn(2, 5, in_dim, generator=gen)
    grad_out = torch.randn(2, 5, out_dim, generator=gen)
    hidden = HiddenLayer(kernels)

    def outputs_and_grads(forward):
        probe.zero_grad(set_to_none=True)
        xi = x.clone().requires_grad_(True)
        y = forward(xi)
        (y * grad_out).sum().backward()
        return [("output", y.detach())] + [(name, p.grad) for name, p in probe.named_parameters()] + [("input", xi.grad)]

    ours = outputs_and_grads(lambda xi: ensemble_mlp(xi, list(probe.weights), list(probe.biases), tanh_output, hidden))
    probe.cpu_forward = None  # the network's own forward, autograd for the gradients
    ref = outputs_and_grads(probe)
    for (name, a), (_, b) in zip(ours, ref):
        if a is None or b is None or a.shape != b.shape:
            return f"give no {name} gradient of its shape"
        error = float((a - b).norm() / b.norm().clamp(min=1e-12))
        if not error <= _TOLERANCE[kernels.dtype]:
            return f"differ from autograd in the {name} (relative error {error:.2g})"
    return None
