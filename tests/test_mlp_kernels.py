"""The hand-written MLP forward/backward (``fast.mlp_kernels``) must be the network's own
autograd maths, on every shape the product trains, and step aside where it is not."""

import pytest
import torch

from offline_rl_core.fast import FastPath
from offline_rl_core.fast.kernel_choice import Kernels, native_bf16, onednn_linear_available
from offline_rl_core.fast.mlp_kernels import HiddenLayer, covers, disagreement_with_autograd, ensemble_mlp
from offline_rl_core.learners import LEARNERS, TrainConfig
from offline_rl_core.learners.networks import EnsembleMLP

BACKENDS = ["blas"] + (["onednn"] if onednn_linear_available() else [])


def with_kernels(net: EnsembleMLP, kernels: Kernels) -> EnsembleMLP:
    """``net`` running on the hand-written kernels ``kernels`` (its autograd forward when
    ``cpu_forward`` is None again)."""
    hidden = HiddenLayer(kernels)
    net.cpu_forward = lambda x, w, b, tanh: ensemble_mlp(x, w, b, tanh, hidden)
    return net


def autograd_of(net: EnsembleMLP):
    def forward(x):
        saved, net.cpu_forward = net.cpu_forward, None
        try:
            return net(x)
        finally:
            net.cpu_forward = saved
    return forward


def _outputs_and_grads(net, fn, x, grad_out):
    net.zero_grad(set_to_none=True)
    x = x.detach().clone().requires_grad_(True)
    y = fn(x)
    (y * grad_out).sum().backward()
    return [y.detach()] + [p.grad for p in net.parameters()] + [x.grad]


def networks_of(learner) -> dict[str, EnsembleMLP]:
    found = {}
    for name, value in vars(learner).items():
        if isinstance(value, EnsembleMLP):
            found[name] = value
        elif hasattr(value, "__dict__"):
            found.update({f"{name}.{k}": v for k, v in vars(value).items() if isinstance(v, EnsembleMLP)})
    return found


# (obs_dim, act_dim) of the tasks, and the widths and batches the product trains with:
# the chapter's (256, 256) and the smoke settings (64, 64)
TASK_DIMS = [(8, 2)]
SETTINGS = [(256, 256), (64, 64)]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("algo", sorted(LEARNERS))
def test_every_network_the_learners_build_matches_autograd(algo, backend):
    """Each learner's networks (policy, critics, value), at the product's widths, batch sizes
    and ensemble sizes, give autograd's outputs and gradients on the hand-written kernels."""
    for obs_dim, act_dim in TASK_DIMS:
        for hidden, batch in SETTINGS:
            for members in (1, 3):
                cfg = TrainConfig(algo=algo, hidden=hidden, batch_size=batch, deterministic=True)
                gens = [torch.Generator().manual_seed(m) for m in range(members)]
                learner = LEARNERS[algo](cfg, members, gens, obs_dim, act_dim)
                for name, net in networks_of(learner).items():
                    assert covers(net), name
                    with_kernels(net, Kernels("fp32", backend, backend, backend))
                    gen = torch.Generator().manual_seed(1)
                    x = torch.randn(net.members, batch, net.in_dim, generator=gen)
                    grad_out = torch.randn(net.members, batch, net.out_dim, generator=gen)
                    ours = _outputs_and_grads(net, net, x, grad_out)
                    ref = _outputs_and_grads(net, autograd_of(net), x, grad_out)
                    for a, b in zip(ours, ref):
                        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5,
                                                   msg=lambda m: f"{algo} {name} {obs_dim}/{hidden}/{batch}: {m}")


class FourLayers(EnsembleMLP):
    """A network the kernels were not written for: one more hidden layer."""

    def __init__(self, members, in_dim, hidden, out_dim, generators=None, tanh_output=False):
        super().__init__(members, in_dim, hidden, out_dim, generators, tanh_output)
        weights, biases = list(self.weights), list(self.biases)
        weights.insert(2, torch.nn.Parameter(torch.randn(members, hidden, hidden) * 0.05))
        biases.insert(2, torch.nn.Parameter(torch.zeros(members, 1, hidden)))
        self.weights, self.biases = torch.nn.ParameterList(weights), torch.nn.ParameterList(biases)


class LayerNormed(EnsembleMLP):
    """The same three layers, with a normalisation the hand-written kernels know nothing of."""

    def forward(self, x):
        if self.cpu_forward is not None:
            return self.cpu_forward(x, list(self.weights), list(self.biases), self.tanh_output)
        h = torch.nn.functional.layer_norm(torch.baddbmm(self.biases[0], x, self.weights[0]).relu(), (self.hidden,))
        h = torch.baddbmm(self.biases[1], h, self.weights[1]).relu()
        y = torch.baddbmm(self.biases[2], h, self.weights[2])
        return y.tanh() if self.tanh_output else y


@pytest.mark.parametrize("cls", [FourLayers, LayerNormed])
def test_a_network_the_kernels_do_not_cover_trains_with_autograd(cls):
    net = cls(2, 8, 32, 2, tanh_output=True)
    cfg = TrainConfig(hidden=32, batch_size=16, deterministic=True)
    assert FastPath().network_forward(net, cfg) is None
    assert net.cpu_forward is None and net.kernels == "autograd"
    x = torch.randn(2, 16, 8)
    net(x).sum().backward()  # autograd trains it
    assert all(p.grad is not None for p in net.parameters())


def test_the_plain_network_gets_the_fast_forward():
    net = EnsembleMLP(2, 8, 32, 2, tanh_output=True)
    fast = FastPath().network_forward(net, TrainConfig(hidden=32, batch_size=16, deterministic=True))
    assert fast is not None and fast[1].startswith("fp32 (")
    assert disagreement_with_autograd(net, HiddenLayer(Kernels())) is None


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("members,tanh_output,out_dim", [(1, True, 2), (2, False, 1), (3, True, 3)])
def test_fp32_forward_and_gradients_match_autograd(members, tanh_output, out_dim, backend):
    torch.manual_seed(0)
    net = with_kernels(EnsembleMLP(members, 7, 32, out_dim, tanh_output=tanh_output), Kernels("fp32", backend, backend, backend))
    x, grad_out = torch.randn(members, 19, 7), torch.randn(members, 19, out_dim)
    ours = _outputs_and_grads(net, net, x, grad_out)
    ref = _outputs_and_grads(net, autograd_of(net), x, grad_out)
    for a, b in zip(ours, ref):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_members_do_not_depend_on_each_other():
    torch.manual_seed(1)
    net = with_kernels(EnsembleMLP(2, 5, 16, 1), Kernels())
    x = torch.randn(2, 9, 5)
    y = net(x)
    x2 = x.clone()
    x2[1] += 1.0  # change member 1's input only
    assert torch.equal(net(x2)[0], y[0])


@pytest.mark.skipif(not native_bf16(), reason="no native bf16 on this CPU")
@pytest.mark.parametrize("backend", BACKENDS)
def test_bf16_hidden_layer_is_within_bf16_rounding(backend):
    torch.manual_seed(2)
    net = with_kernels(EnsembleMLP(2, 10, 256, 1), Kernels("bf16", backend, backend, backend))
    x, grad_out = torch.randn(2, 256, 10), torch.randn(2, 256, 1)
    ours = _outputs_and_grads(net, net, x, grad_out)
    ref = _outputs_and_grads(net, autograd_of(net), x, grad_out)
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
    # a choice only the cache knows: the other backend for the forward, and a mark a new
    # measurement would overwrite
    entry["forward"] = "blas" if entry["forward"] == "onednn" else "onednn"
    entry["measured"] = "written by the test"
    cache.write_text(json.dumps({k: entry for k in entries}))
    second = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert second.startswith(f"fp32 (forward {entry['forward']},"), (first, second)
    assert json.loads(cache.read_text()) == {k: entry for k in entries}  # read, not measured again


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
