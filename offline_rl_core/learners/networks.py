"""The one MLP every learner uses, in ensemble form.

``EnsembleMLP`` holds E independent ``in -> hidden -> hidden -> out`` ReLU networks as
stacked weights, and runs them as one batched product per layer for all members, with
autograd for the gradients. A speed layer may give a network a faster CPU forward of the
same maths (``acceleration``; ``offline_rl_core.fast`` runs members one by one through
hand-written kernels, checked against this one). A
single policy is E=1; the twin critics of one run are E=2; three seeds trained
together are E=3 policies and E=6 critics. Members never share parameters, and Adam
is elementwise, so training E members together is the same maths as training them
one by one -- just fewer, larger kernels.
"""

from __future__ import annotations

import math

import torch
from torch import nn



class EnsembleMLP(nn.Module):
    def __init__(
        self,
        members: int,
        in_dim: int,
        hidden: int,
        out_dim: int,
        generators: list[torch.Generator] | None = None,
        tanh_output: bool = False,
    ):
        super().__init__()
        self.members, self.in_dim, self.hidden, self.out_dim = members, in_dim, hidden, out_dim
        self.tanh_output = tanh_output
        # a speed layer's CPU forward of the same maths (``acceleration``), and what it runs on
        self.cpu_forward = None
        self.kernels = "autograd"
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
        if self.cpu_forward is not None and x.is_cpu:
            return self.cpu_forward(x, list(self.weights), list(self.biases), self.tanh_output)
        h = x
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            h = torch.baddbmm(b, h, w)
            if i < len(self.weights) - 1:
                h = h.relu()
        return h.tanh() if self.tanh_output else h

    def member_state(self, m: int) -> dict[str, torch.Tensor]:
        """Member m as plain Linear weights ``{'0.weight' (out,in), '0.bias', ...}``:
        the checkpoint form, loadable into ``serving.policy.policy_sequential`` or numpy."""
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

