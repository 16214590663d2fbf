"""Training steps without autograd: the backward written out, Adam called directly.

``awac.py`` and ``bc.py`` are the readable definitions of their updates and run
through autograd and ``torch.optim``. On a CPU their per-op Python is about a quarter
of an AWAC step (3.3 ms in bf16 here), so training runs the same updates from here
instead: the same ATen ops in the same order, with autograd's backward formulas
written out, hence the same bytes (tests/test_written_out.py checks weights, targets,
losses and |Q| against autograd).

AWAC's step also exists in C++ (``csrc/awac_step.cpp`` via ``awac_cpp``, compiled
once): 2.2 ms a bf16 step here, against 2.5 ms for the Python below. BC (and filtered
BC) take the Python step. ``PUSHER_RL_STEP`` picks: ``auto`` (default: C++ where it
builds, else Python), ``cpp``, ``python`` or ``autograd``.
"""

from __future__ import annotations

import os
import sys

import torch

from ..errors import UserError
from ..mlp_kernels import HiddenLayer, mlp_backward, mlp_forward

STEP_ENV = "PUSHER_RL_STEP"
STEP_MODES = ("auto", "cpp", "python", "autograd")


def adam_state(opt: torch.optim.Adam) -> tuple:
    """(params, exp_avgs, exp_avg_sqs, steps, lr, betas, eps, weight_decay) of a fused
    Adam, its state created exactly as ``Adam.step`` creates it on first use (so the
    optimiser's ``state_dict`` stays valid whichever path stepped it). The steps take
    it once, when built: ``_fused_adam_`` updates these tensors in place."""
    group = opt.param_groups[0]
    if len(opt.param_groups) != 1 or not group["fused"] or group["amsgrad"] or group["maximize"] \
            or group.get("decoupled_weight_decay", False):
        raise ValueError("the written-out AWAC step needs one param group of plain fused Adam")
    params = group["params"]
    for p in params:
        state = opt.state[p]
        if not state:
            state["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
            state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
    states = [opt.state[p] for p in params]
    return (params, [s["exp_avg"] for s in states], [s["exp_avg_sq"] for s in states], [s["step"] for s in states],
            float(group["lr"]), group["betas"], float(group["eps"]), float(group["weight_decay"]))


def _adam_step(state: tuple, grads: list[torch.Tensor]) -> None:
    """What ``Adam(fused=True).step()`` runs, given the gradients."""
    params, exp_avgs, exp_avg_sqs, steps, lr, (beta1, beta2), eps, weight_decay = state
    torch._foreach_add_(steps, 1)
    torch._fused_adam_(params, grads, exp_avgs, exp_avg_sqs, [], steps, lr=lr, beta1=beta1, beta2=beta2,
                       weight_decay=weight_decay, eps=eps, amsgrad=False, maximize=False)


def _forward(params, x, tanh_output: bool, hidden: HiddenLayer, saved: list | None, w2c=None, b2c=None):
    """The network's forward (``mlp_kernels.mlp_forward``); ``saved`` collects what
    ``_backward`` needs."""
    w1, w2, w3, b1, b2, b3 = params
    y, w2c, acts = mlp_forward(x, w1, b1, w2, b2, w3, b3, tanh_output, hidden, w2c, b2c)
    if saved is not None:
        saved.extend([x, w2c, y, acts])
    return y


def _backward(params, saved: list, grad_y, tanh_output: bool, hidden: HiddenLayer) -> list[torch.Tensor]:
    """Parameter gradients in parameter order (w1, w2, w3, b1, b2, b3); no input
    gradient (neither update needs one)."""
    w1, w2, w3, b1, b2, b3 = params
    x, w2c, y, acts = saved
    _, gw1, gb1, gw2, gb2, gw3, gb3 = mlp_backward(grad_y, x, w1, w2c, w3, y, acts, tanh_output, hidden, False)
    return [gw1, gw2, gw3, gb1, gb2, gb3]


def _pairs(obs, action):
    x = torch.cat([obs, action], -1)
    m, b, d = x.shape
    return x.unsqueeze(1).expand(m, 2, b, d).reshape(2 * m, b, d)


class AWACStep:
    """One AWAC update, written out (the C++ step mirrors this line for line)."""

    def __init__(self, learner):
        self.learner = learner
        self.hid = learner.policy.hidden_layer
        self.pol_state, self.q_state = adam_state(learner.policy_opt), adam_state(learner.critic.opt)
        self.q_target = list(learner.critic.target.parameters())

    def __call__(self, batch) -> dict[str, torch.Tensor]:
        learner, cfg, hid = self.learner, self.learner.cfg, self.hid
        pol_state, q_state, q_target = self.pol_state, self.q_state, self.q_target
        pol, q = pol_state[0], q_state[0]
        obs, action = batch.obs, batch.action
        members = obs.shape[0]
        with torch.inference_mode():
            # critic target: r + gamma (1 - done) min Q'(s', pi(s'))
            pw2c, pb2c = pol[1].to(hid.dtype), pol[4].to(hid.dtype)  # shared by both policy calls
            next_action = _forward(pol, batch.next_obs, True, hid, None, pw2c, pb2c)
            qn = _forward(q_target, _pairs(batch.next_obs, next_action), False, hid, None)
            next_q = qn.view(members, 2, *qn.shape[1:]).min(1)[0]
            target_q = batch.reward + torch.mul(batch.not_done, cfg.gamma) * next_q

            # critics: MSE of both toward the target; autograd's chain for
            # sum(1) <- mean(2) <- pow(2) is ones / n * 2 * diff
            saved: list = []
            qy = _forward(q, _pairs(obs, action), False, hid, saved)
            diff = qy.view(members, 2, *qy.shape[1:]) - target_q.unsqueeze(1)
            critic_loss = diff.pow(2).flatten(2).mean(2).sum(1)
            n = diff.shape[2] * diff.shape[3]
            grad = torch.ones(members, 2, n).div(n).view(diff.shape) * torch.mul(diff.pow(1.0), 2.0)
            _adam_step(q_state, _backward(q, saved, grad.view(qy.shape), False, hid))

            # actor: advantage-weighted regression (weight without gradient)
            saved = []
            pred = _forward(pol, obs, True, hid, saved, pw2c, pb2c)
            both = _forward(q, _pairs(torch.cat([obs, obs], 1), torch.cat([action, pred], 1)), False, hid, None)
            q_data, value = both.view(members, 2, *both.shape[1:]).min(1)[0].chunk(2, 1)
            weight = torch.clamp(torch.exp(torch.div(q_data - value, cfg.beta)), None, cfg.weight_clip)
            pdiff = pred - action
            weighted = weight * pdiff.pow(2).mean(-1, keepdim=True)
            policy_loss = (weighted * batch.actor_mask).flatten(1).mean(1)
            n = weighted.shape[1] * weighted.shape[2]
            grad = torch.ones(members, n).div(n).view(weighted.shape) * batch.actor_mask * weight
            grad = grad.expand(pdiff.shape).div(pdiff.shape[2])
            _adam_step(pol_state, _backward(pol, saved, grad * torch.mul(pdiff.pow(1.0), 2.0), True, hid))

            torch._foreach_lerp_(q_target, q, learner.critic.tau)
            return {"critic_loss": critic_loss / 2, "policy_loss": policy_loss}


class BCStep:
    """One BC update (``bc.py``), written out."""

    def __init__(self, learner):
        self.hid = learner.policy.hidden_layer
        self.pol_state = adam_state(learner.policy_opt)

    def __call__(self, batch) -> dict[str, torch.Tensor]:
        pol_state, hid = self.pol_state, self.hid
        pol = pol_state[0]
        members = batch.obs.shape[0]
        with torch.inference_mode():
            saved: list = []
            pdiff = _forward(pol, batch.obs, True, hid, saved) - batch.action
            err = pdiff.pow(2).mean(-1, keepdim=True)
            loss = (err * batch.actor_mask).flatten(1).mean(1)
            n = err.shape[1] * err.shape[2]
            grad = torch.ones(members, n).div(n).view(err.shape) * batch.actor_mask
            grad = grad.expand(pdiff.shape).div(pdiff.shape[2])
            _adam_step(pol_state, _backward(pol, saved, grad * torch.mul(pdiff.pow(1.0), 2.0), True, hid))
            return {"policy_loss": loss}


_notified = False


def _notice(line: str) -> None:
    global _notified
    if not _notified:
        print(f"pusher-rl: {line}", file=sys.stderr, flush=True)
        _notified = True


def step_mode() -> str:
    mode = os.environ.get(STEP_ENV, "auto").strip().lower() or "auto"
    if mode not in STEP_MODES:
        raise UserError(f"{STEP_ENV}={mode}: expected one of {', '.join(STEP_MODES)}")
    return mode


def written_out_step(learner, kind: str):
    """The written-out ``kind`` ("awac" or "bc") update for ``learner``, or None where
    autograd's must run: on a GPU (the CUDA graph already removes the per-op cost),
    or under ``PUSHER_RL_STEP=autograd``."""
    mode = step_mode()
    if mode == "autograd" or learner.policy.weights[0].device.type != "cpu":
        return None
    if kind == "bc":
        return BCStep(learner)
    if mode in ("auto", "cpp"):
        from . import awac_cpp

        reason = awac_cpp.unavailable_reason()
        if reason is None:
            return awac_cpp.CppStep(learner)
        if mode == "cpp":
            raise UserError(f"{STEP_ENV}=cpp: the C++ AWAC step cannot be built here: {reason}")
        _notice(f"the C++ AWAC step is not available ({reason}); using the Python step (about 1.1x slower)")
    return AWACStep(learner)
