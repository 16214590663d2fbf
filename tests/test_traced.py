"""The fast path is derived from each learner's one definition: the recorded and
replayed step gives the same bytes as running ``update`` with autograd, every learner
takes it, and an edit to a learner's loss changes what trains."""

import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.fast.kernel_choice import native_bf16
from offline_rl_core.learners import ALGORITHMS, TrainConfig, train_seeds
from offline_rl_core.learners.awac import AWAC
from offline_rl_core.learners.base import per_member_mean, regression_error
from offline_rl_core.learners.loop import LEARNERS

has_compiler = shutil.which("g++") is not None and shutil.which("ninja") is not None
REPLAYS = ["python"] + (["cpp"] if has_compiler else [])
CFG = dict(steps=40, log_every=10, batch_size=64, hidden=64)


@pytest.fixture(scope="module")
def data():
    return collect_transitions(20, 0.3, 0)


def _run(monkeypatch, data, mode: str, algo: str, seeds=(0, 1), **overrides):
    monkeypatch.setenv("PUSHER_RL_STEP", mode)
    return train_seeds(data, TrainConfig(algo=algo, **{**CFG, **overrides}), list(seeds))


def _tensors(checkpoint) -> dict:
    flat = {f"policy.{k}": v for k, v in checkpoint["policy_state"].items()}
    for name, part in checkpoint["learner_state"].items():
        flat.update({f"{name}.{k}": v for k, v in part.items()} if isinstance(part, dict) else {name: part})
    return flat


def _assert_same_bytes(got, want):
    for g, w in zip(got, want):
        tg, tw = _tensors(g.checkpoint), _tensors(w.checkpoint)
        assert tg.keys() == tw.keys()
        for key in tw:
            np.testing.assert_array_equal(tg[key].numpy(), tw[key].numpy(), err_msg=key)
        assert g.history == w.history
        assert g.mean_abs_q == w.mean_abs_q


@pytest.mark.parametrize("replay", REPLAYS)
@pytest.mark.parametrize("algo", ALGORITHMS)
def test_replayed_step_is_byte_identical_to_autograd(monkeypatch, data, algo, replay):
    want = _run(monkeypatch, data, "autograd", algo)
    got = _run(monkeypatch, data, replay, algo)
    assert {r.step_kind for r in got} == {replay}
    assert {r.step_kind for r in want} == {"eager"}
    _assert_same_bytes(got, want)


@pytest.mark.skipif(not native_bf16(), reason="no native bf16 on this CPU")
def test_replay_is_byte_identical_in_bf16_too(monkeypatch, data):
    monkeypatch.setenv("PUSHER_RL_KERNELS", "bf16")
    want = _run(monkeypatch, data, "autograd", "awac", deterministic=False)
    got = _run(monkeypatch, data, "auto", "awac", deterministic=False)
    assert "bf16" in got[0].checkpoint["kernels"]
    _assert_same_bytes(got, want)


def test_every_learner_takes_the_fast_path_by_default(monkeypatch, data):
    monkeypatch.delenv("PUSHER_RL_STEP", raising=False)
    for algo in LEARNERS:
        result = train_seeds(data, TrainConfig(algo=algo, **{**CFG, "steps": 5}), [0])[0]
        assert result.step_kind in REPLAYS, algo
        assert result.checkpoint["train_step"] == result.step_kind


class SquaredWeightAWAC(AWAC):
    """A researcher's edit: AWAC with the advantage weight squared."""

    def actor_loss(self, batch):
        pred = self.policy(batch.obs)
        with torch.no_grad():
            both = self.critic.q_min(torch.cat([batch.obs, batch.obs], 1), torch.cat([batch.action, pred], 1))
            q_data, value = both.chunk(2, dim=1)
            weight = torch.exp((q_data - value) / self.cfg.beta).clamp(max=self.cfg.weight_clip).pow(2)
        return per_member_mean(weight * regression_error(pred, batch.action) * batch.actor_mask)


def test_a_subclassed_loss_trains_on_the_default_path(monkeypatch, data):
    plain = _run(monkeypatch, data, "auto", "awac", seeds=[0])
    monkeypatch.setitem(LEARNERS, "awac", SquaredWeightAWAC)
    edited = _run(monkeypatch, data, "auto", "awac", seeds=[0])
    assert edited[0].step_kind in REPLAYS
    assert edited[0].history["policy_loss"] != plain[0].history["policy_loss"]
    _assert_same_bytes(edited, _run(monkeypatch, data, "autograd", "awac", seeds=[0]))


def test_a_monkeypatched_loss_trains_on_the_default_path(monkeypatch, data):
    plain = _run(monkeypatch, data, "auto", "bc", seeds=[0])

    def absolute_error(self, batch):  # L1 instead of the squared error
        loss = per_member_mean((self.policy(batch.obs) - batch.action).abs().mean(-1, keepdim=True) * batch.actor_mask)
        self.step_policy(loss)
        return {"policy_loss": loss.detach()}

    from offline_rl_core.learners.bc import BC

    monkeypatch.setattr(BC, "update", absolute_error)
    edited = _run(monkeypatch, data, "auto", "bc", seeds=[0])
    assert edited[0].step_kind in REPLAYS
    assert edited[0].history["policy_loss"] != plain[0].history["policy_loss"]
    _assert_same_bytes(edited, _run(monkeypatch, data, "autograd", "bc", seeds=[0]))


def test_draws_from_a_learners_own_generator_replay_like_eager(monkeypatch, data):
    """Noise drawn inside update from a generator the learner owns (as a stochastic
    policy would) replays exactly as the eager step draws it."""
    from offline_rl_core.learners.bc import BC

    def noisy_targets(self, batch):
        if not hasattr(self, "noise_gen"):
            self.noise_gen = torch.Generator().manual_seed(7)
        noise = torch.randn(batch.action.shape, generator=self.noise_gen) * 0.1
        loss = per_member_mean(regression_error(self.policy(batch.obs), batch.action + noise))
        self.step_policy(loss)
        return {"policy_loss": loss.detach()}

    monkeypatch.setattr(BC, "update", noisy_targets)
    got = _run(monkeypatch, data, "auto", "bc", seeds=[0])
    assert got[0].step_kind in REPLAYS
    _assert_same_bytes(got, _run(monkeypatch, data, "autograd", "bc", seeds=[0]))


READ_BACKS = {
    "float": lambda t: float(t),
    "numpy": lambda t: float(t.detach().numpy()),  # reads memory without an operator call
    "tolist": lambda t: t.detach().tolist(),
}


@pytest.mark.parametrize("read", sorted(READ_BACKS))
def test_an_update_that_reads_a_tensor_back_runs_eagerly(monkeypatch, data, capsys, read):
    """A value read back from a tensor cannot be replayed (the replay would keep the one
    read while recording): the learner runs eagerly, says so, and trains exactly as
    autograd."""
    from offline_rl_core.learners.bc import BC

    def scaled_by_its_own_error(self, batch):
        err = regression_error(self.policy(batch.obs), batch.action)
        loss = per_member_mean(err) / READ_BACKS[read](err.mean())
        self.step_policy(loss)
        return {"policy_loss": loss.detach()}

    monkeypatch.setattr(BC, "update", scaled_by_its_own_error)
    got = _run(monkeypatch, data, "auto", "bc", seeds=[0])
    assert got[0].step_kind == "not recordable"
    assert "eagerly" in capsys.readouterr().err
    _assert_same_bytes(got, _run(monkeypatch, data, "autograd", "bc", seeds=[0]))


def test_a_refused_recording_is_undone_for_loose_parameters_too(monkeypatch, data):
    """SAC's log-std is a parameter of its own, outside any module: the recording that
    stops after the optimiser's step must undo that step for it too, or the eager step
    taken instead applies it twice."""
    from offline_rl_core.learners.sac import SAC

    plain_update = SAC.update

    def update_then_read_back(self, batch):
        losses = plain_update(self, batch)
        float(losses["critic_loss"].sum())  # after every optimiser step: refused at the end
        return losses

    monkeypatch.setattr(SAC, "update", update_then_read_back)
    got = _run(monkeypatch, data, "auto", "sac", seeds=[0])
    assert got[0].step_kind == "not recordable"
    _assert_same_bytes(got, _run(monkeypatch, data, "autograd", "sac", seeds=[0]))


def test_without_the_cpp_replay_the_default_trains_the_cpp_bytes(monkeypatch, data):
    """The Python replay and plain autograd run on one thread unless told otherwise, so
    a machine without a compiler trains what one with it does."""
    monkeypatch.delenv("PUSHER_RL_STEP", raising=False)
    cfg = {**CFG, "batch_size": 256, "hidden": 256, "steps": 12, "log_every": 4}
    want = train_seeds(data, TrainConfig(algo="awac", **cfg), [0])
    for mode in ("python", "autograd"):
        _assert_same_bytes(_run(monkeypatch, data, mode, "awac", seeds=[0], **cfg), want)


@pytest.mark.skipif(not has_compiler, reason="no g++ / ninja")
def test_build_command_reports_ready():
    proc = subprocess.run([sys.executable, "-m", "offline_rl_core.fast.graph_runner"], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "C++ step replayer ready" in proc.stdout


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

    from offline_rl_core.fast.graph_runner import _clear_stale_lock

    lock = tmp_path / "lock"
    lock.write_text("")
    _clear_stale_lock(tmp_path)
    assert lock.exists()
    old = time.time() - 3600
    os.utime(lock, (old, old))
    _clear_stale_lock(tmp_path)
    assert not lock.exists()


@pytest.mark.skipif(not has_compiler, reason="no g++ / ninja")
@pytest.mark.parametrize("algo", ALGORITHMS)
def test_a_step_replayed_on_several_threads_gives_the_same_bytes(monkeypatch, data, algo):
    """The step's calls spread over threads (``--threads``) train exactly what one
    thread trains: every call waits for what it reads and for what it overwrites,
    views and random draws included (SAC samples its actions inside the step)."""
    one = _run(monkeypatch, data, "cpp", algo, threads=1)
    several = _run(monkeypatch, data, "cpp", algo, threads=3)
    assert {r.checkpoint["train_threads"] for r in one} == {1}
    assert {r.checkpoint["train_threads"] for r in several} == {3}
    _assert_same_bytes(several, one)


@pytest.mark.skipif(not has_compiler, reason="no g++ / ninja: the Python replay runs on one thread")
def test_the_default_step_is_offered_every_free_core(monkeypatch, data):
    """By default the C++ replay may use every core this process may run on, and uses at
    most that many (how many pay is measured: bench/, not here); a number given is used
    as it is."""
    from offline_rl_core.common.machine import available_cores
    from offline_rl_core.learners.data import MemberData
    from offline_rl_core.learners.stepper import make_step

    monkeypatch.delenv("PUSHER_RL_STEP", raising=False)
    cfg = TrainConfig(algo="awac", **CFG)
    learner = LEARNERS["awac"](cfg, 1, [torch.Generator().manual_seed(0)], data.obs.shape[1], data.action.shape[1])
    step = make_step(learner.update, MemberData([data]), (1, cfg.batch_size), "cpu", True)
    for _ in range(4):  # eager, recorded, then replayed and timed
        step(torch.zeros((1, cfg.batch_size), dtype=torch.long))
    assert step.kind == "cpp"
    assert step.replay.program.workers == available_cores()
    assert 1 <= step.threads <= available_cores()
    result = train_seeds(data, TrainConfig(algo="awac", **{**CFG, "steps": 12, "threads": 2}), [0])[0]
    assert result.step_kind == "cpp" and result.checkpoint["train_threads"] == 2


@pytest.mark.skipif(not has_compiler, reason="no g++ / ninja")
def test_a_call_failing_on_a_helper_thread_raises_and_training_goes_on(monkeypatch, data):
    """An error inside a step run on several threads comes back as an exception (no
    hang, no lost thread), and the next step runs."""
    from offline_rl_core.learners.data import MemberData
    from offline_rl_core.learners.stepper import make_step

    monkeypatch.setenv("PUSHER_RL_STEP", "cpp")
    cfg = TrainConfig(algo="awac", **CFG)
    learner = LEARNERS["awac"](cfg, 1, [torch.Generator().manual_seed(0)], data.obs.shape[1], data.action.shape[1])
    step = make_step(learner.update, MemberData([data]), (1, cfg.batch_size), "cpu", True, threads=2)
    good = torch.zeros((1, cfg.batch_size), dtype=torch.long)
    for _ in range(4):  # eager, recorded, timed, then on two threads
        step(good)
    assert step.kind == "cpp" and step.replay.program.workers == 2
    with pytest.raises(IndexError, match="out of range"):
        step(torch.full((1, cfg.batch_size), len(data) + 5, dtype=torch.long))
    losses = step(good)
    assert all(torch.isfinite(v).all() for v in losses.values())


@pytest.fixture(scope="module")
def undeclared_view_op():
    """An operator whose schema says it returns a new tensor while it returns a view,
    as a third-party extension's might."""
    lib = torch.library.Library("pusher_rl_test", "DEF")
    lib.define("same_memory(Tensor x) -> Tensor")
    lib.impl("same_memory", lambda x: x.view(x.shape), "CPU")
    yield torch.ops.pusher_rl_test.same_memory
    del lib


@pytest.mark.skipif(not has_compiler, reason="no g++ / ninja")
def test_memory_shared_behind_the_schemas_back_runs_on_one_thread(monkeypatch, data, capsys, undeclared_view_op):
    """Threads trust the operators' alias annotations; where a value really shares memory
    they do not declare and something writes it, the timed replay sees it and the steps
    stay on one thread, with a notice, and train what the eager step trains."""
    from offline_rl_core.learners.bc import BC

    def update_through_a_hidden_view(self, batch):
        with torch.no_grad():
            target = batch.action.clone()
            undeclared_view_op(target).mul_(0.5)  # overwrites target's memory
        loss = per_member_mean(regression_error(self.policy(batch.obs), target))
        self.step_policy(loss)
        return {"policy_loss": loss.detach()}

    monkeypatch.setattr(BC, "update", update_through_a_hidden_view)
    got = _run(monkeypatch, data, "cpp", "bc", seeds=[0], threads=2)
    assert "training steps run on one thread" in capsys.readouterr().err
    assert got[0].step_kind == "cpp" and got[0].checkpoint["train_threads"] == 1
    _assert_same_bytes(got, _run(monkeypatch, data, "autograd", "bc", seeds=[0]))
