"""The one MLP every learner uses, in ensemble form.

``EnsembleMLP`` holds E independent ``in -> hidden -> hidden -> out`` ReLU networks as
stacked weights. On the CPU they run member by member through the hand-written kernels of
``mlp_kernels``; on a GPU, one batched product per layer for all members. A
single policy is E=1; the twin critics of one run are E=2; three seeds trained
together are E=3 policies and E=6 critics. Members never share parameters, and Adam
is elementwise, so training E members together is the same maths as training them
one by one -- just fewer, larger kernels.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .kernel_choice import Kernels
from .mlp_kernels import HiddenLayer, ensemble_mlp


class EnsembleMLP(nn.Module):
    def __init__(
        self,
        members: int,
        in_dim: int,
        hidden: int,
        out_dim: int,
        generators: list[torch.Generator] | None = None,
        tanh_output: bool = False,
        kernels: Kernels | None = None,
    ):
        super().__init__()
        self.members, self.in_dim, self.hidden, self.out_dim = members, in_dim, hidden, out_dim
        self.tanh_output = tanh_output
        # the hidden layer's products on the CPU (parameters stay fp32 whatever their dtype)
        self.hidden_layer = HiddenLayer(kernels)
        dims = [in_dim, hidden, hidden, out_dim]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for d_in, d_out in zip(dims[:-1], dims[1:]):
            self.weights.append(nn.Parameter(torch.empty(members, d_in, d_out)))
            self.biases.append(nn.Parameter(torch.empty(members, 1, d_out)))
        self.reset_parameters(generators)

    @torch.no_grad()
    def reset_parameters(self, generators: list[torch.Generator] | None = None) -> None:
        """PyTorch's nn.Linear default init, U(-1/sqrt(fan_in), 1/sqrt(fan_in)), drawn
        member by member from that member's generator so each member is reproducible
        on its own, whatever else is in the ensemble."""
        for m in range(self.members):
            gen = generators[m] if generators is not None else None
            for w, b in zip(self.weights, self.biases):
                bound = 1.0 / math.sqrt(w.shape[1])
                w[m].uniform_(-bound, bound, generator=gen)
                b[m].uniform_(-bound, bound, generator=gen)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (E, B, in) -> (E, B, out)."""
        if not x.is_cpu:
            return self._forward_batched(x)
        return ensemble_mlp(x, list(self.weights), list(self.biases), self.tanh_output, self.hidden_layer)

    def _forward_batched(self, x: torch.Tensor) -> torch.Tensor:
        """On a GPU: one batched product per layer for all members, in fp32, autograd for
        the backward. The CPU's hand-written member-by-member kernels exist to cut per-op
        overhead, which a replayed CUDA graph has already removed."""
        (w1, w2, w3), (b1, b2, b3) = self.weights, self.biases
        h = torch.baddbmm(b1, x, w1).relu()
        h = torch.baddbmm(b2, h, w2).relu()
        y = torch.baddbmm(b3, h, w3)
        return y.tanh() if self.tanh_output else y

    def member_state(self, m: int) -> dict[str, torch.Tensor]:
        """Member m as plain Linear weights ``{'0.weight' (out,in), '0.bias', ...}``:
        the checkpoint form, loadable into ``policy_sequential`` or numpy."""
        state = {}
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            state[f"{2 * i}.weight"] = w[m].detach().t().contiguous().clone().cpu()
            state[f"{2 * i}.bias"] = b[m, 0].detach().clone().cpu()
        return state

    @torch.no_grad()
    def load_member_state(self, m: int, state: dict[str, torch.Tensor]) -> None:
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            w[m].copy_(state[f"{2 * i}.weight"].t())
            b[m, 0].copy_(state[f"{2 * i}.bias"])


def policy_sequential(obs_dim: int, hidden: int, act_dim: int) -> nn.Sequential:
    """A single policy as ordinary layers (the form exported to ONNX); tanh is applied
    by the caller (see ``offline_rl_core.policy``)."""
    return nn.Sequential(
        nn.Linear(obs_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, act_dim)
    )
