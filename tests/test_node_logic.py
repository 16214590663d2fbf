"""The nodes' logic as plain classes, tested without DDS: the sim's protocol
(offline_rl_core.nodes.sim_loop), stamp pairing (pairing) and joint messages (joint_messages)."""

from __future__ import annotations

import numpy as np
import pytest

from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.task.expert import expert_action
from offline_rl_core.nodes.joint_messages import (
    action_from_effort, action_from_torques, joints_from_state, torques_from_action,
)
from offline_rl_core.nodes.pairing import StatePairing
from offline_rl_core.nodes.sim_loop import TICK_NS, SimLoop
from offline_rl_core.data.transitions import SOURCE_EXPERT, Transitions

START = 1_700_000_000 * 1_000_000_000


def test_lockstep_loop_driven_by_the_expert_equals_collect():
    loop = SimLoop("lockstep", seed=4, episodes=2, start_ns=START)
    state, rows = loop.start_episode(), []
    assert state.stamp_ns == START
    while not loop.finished:
        action = expert_action(state.position, state.velocity, state.target[:2])
        assert loop.command(state.stamp_ns + 1, action, SOURCE_EXPERT) is None  # another state's stamp: stale
        step = loop.command(state.stamp_ns, action, SOURCE_EXPERT)
        assert loop.command(state.stamp_ns, action, SOURCE_EXPERT) is None  # answered: the stamp is stale now
        rows.append(step.transition)
        state = step.next_state or step.new_episode
        if step.episode_over and not loop.finished:
            assert state.stamp_ns == START + 100 * TICK_NS  # an episode owns 100 ticks
    assert state is None and loop.summary()["episodes"] == 2
    assert np.array_equal(np.stack(rows), collect_transitions(2, 1.0, 4).to_rows())


def test_realtime_loop_holds_the_latest_command_and_counts_ticks():
    loop = SimLoop("realtime", seed=0, start_ns=START)
    loop.start_episode()
    assert loop.command(None, np.array([1.0, -1.0], np.float32), 3) is None  # held, not stepped
    first, second = loop.tick(), loop.tick()
    assert first.next_state.stamp_ns == START + TICK_NS and second.next_state.stamp_ns == START + 2 * TICK_NS
    assert list(Transitions.from_rows(np.stack([first.transition, second.transition])).source) == [3, 3]
    state = loop.reset()  # the next episode; sim time goes on
    assert loop.episode == 1 and state.stamp_ns == START + 2 * TICK_NS


def test_pairing_waits_for_the_target_and_fingertip_of_the_state():
    p = StatePairing()
    assert p.on_state(1, "s1") is None  # no target yet
    done = p.on_target(1, (0.1, 0.2))
    assert done.state == "s1" and done.fingertip_xy is None and np.allclose(done.target_xy, [0.1, 0.2])
    # co-stamped from now on: a state waits for the target of its own stamp
    assert p.on_state(2, "s2") is None and p.on_target(2, (0.3, 0.4)).state == "s2"
    # once a fingertip has been heard, a state waits for its fingertip too
    assert p.on_fingertip(3, (0.0, 0.1)) is None
    assert p.on_target(3, (0.3, 0.4)) is None and p.on_state(3, "s3").fingertip_xy is not None
    assert p.on_target(4, (0.3, 0.4)) is None and p.on_state(4, "s4") is None
    assert p.on_fingertip(4, (0.0, 0.2)).state == "s4"


def test_pairing_without_co_stamped_targets_uses_the_latest():
    p = StatePairing()
    p.on_target(10, (0.1, 0.2))
    assert p.on_state(11, "s").stamp == 11  # another arm: targets carry their own stamps


def test_joint_messages_read_commands_states_and_torques():
    assert np.array_equal(action_from_effort(["elbow", "shoulder"], [0.5, 1.0])[0], np.float32([1.0, 0.5]))
    # beyond the action range: refused, never clipped to full effort
    assert action_from_effort(["elbow", "shoulder"], [0.5, 2.0])[1].reason == "beyond limits"
    assert action_from_effort([], [1e300, 0.0])[1].reason == "beyond limits"
    assert action_from_effort([], [0.1])[1] == "effort has 1 values, expected 2 (shoulder, elbow)"
    assert action_from_effort([], [float("nan"), 0])[1] == "effort is not finite"
    assert action_from_effort([], [], allow_empty=True) == (None, None)  # a teleop yield
    (q, qd), _ = joints_from_state(["elbow", "shoulder"], [1.0, 2.0], [3.0, 4.0])
    assert list(q) == [2.0, 1.0] and list(qd) == [4.0, 3.0]
    assert joints_from_state([], [0.1], [0.1])[1].reason == "wrong length"
    assert np.allclose(torques_from_action([1.0, -0.4]), [0.5, -0.2])  # motor gear 0.5 N·m
    assert np.allclose(action_from_torques([0.25, -0.5])[0], [0.5, -1.0])
    assert action_from_torques([0.25, -3.0])[1].reason == "beyond limits"  # beyond the motors: refused
    assert action_from_torques([1.0])[1].startswith("expected 2 torques")


def test_sim_loop_refuses_an_unknown_mode():
    with pytest.raises(ValueError, match="mode must be one of realtime, lockstep"):
        SimLoop("fast")


def test_a_state_reports_the_torque_the_motors_applied_in_newton_metres():
    loop = SimLoop("lockstep", seed=0, start_ns=START)
    loop.start_episode()
    loop.command(loop.current.stamp_ns, np.array([1.0, -0.3], np.float32), 2)
    assert np.allclose(loop.current.torque, [0.5, -0.15])  # action x motor gear (0.5 N·m)



# ------------------------------------------------------------------ the policy node's checkpoints
def _checkpoint(**fields):
    import torch

    from offline_rl_core.serving.policy import policy_sequential

    torch.manual_seed(0)
    state = dict(policy_sequential(8, 16, 2).state_dict())
    return {"format": "pusher-rl/policy", "version": 1, "algorithm": "bc", "obs_dim": 8, "act_dim": 2,
            "hidden": 16, "policy_state": state, **fields}


def test_a_checkpoint_whose_biases_or_normalisation_do_not_fit_is_refused_at_load(tmp_path):
    """Refused at load, so the node refuses it at start, on reload, on ``param set`` and as a
    weights message (the old policy serving on), instead of crashing on the next state."""
    import torch

    from offline_rl_core.common.errors import UserError
    from offline_rl_core.serving.weights import encode_weights, policy_from_weights_message
    from offline_rl_core.serving.checkpoint import save_checkpoint
    from offline_rl_core.serving.policy import load_policy
    from offline_rl_core.serving.signing import Signer

    signer = Signer.generate()

    good = _checkpoint()
    state = good["policy_state"]
    bad = {
        "'4.bias' has shape (7,)": _checkpoint(policy_state={**state, "4.bias": torch.zeros(7)}),
        "'0.bias' is missing": _checkpoint(policy_state={k: v for k, v in state.items() if k != "0.bias"}),
        "obs_mean must be obs_dim=8": _checkpoint(obs_mean=torch.zeros(3), obs_std=torch.ones(3)),
        "obs_std must be obs_dim=8": _checkpoint(obs_mean=torch.zeros(8)),  # a mean without a std
        "obs_std must be > 0": _checkpoint(obs_mean=torch.zeros(8), obs_std=torch.zeros(8)),
        "obs_mean must be obs_dim=8 finite": _checkpoint(obs_mean=torch.full((8,), float("nan")), obs_std=torch.ones(8)),
    }
    obs = np.linspace(-1, 1, 8, dtype=np.float32)
    save_checkpoint(tmp_path / "good.pt", _checkpoint(obs_mean=torch.zeros(8), obs_std=torch.full((8,), 2.0)))
    assert np.all(np.abs(load_policy(tmp_path / "good.pt").act(obs)) <= 1)
    for i, (expected, ckpt) in enumerate(bad.items()):
        path = save_checkpoint(tmp_path / f"bad{i}.pt", ckpt)
        with pytest.raises(UserError) as refused:
            load_policy(path)
        assert str(refused.value).startswith(f"{path}: ") and expected in str(refused.value), str(refused.value)
        assert "\n" not in str(refused.value)
        signed = encode_weights({**ckpt, "weights_version": 1}, signer)  # the learner's own key: checked past it
        policy, problem = policy_from_weights_message("pusher-rl/weights", signed, signer.verifier(), "learner/weights")
        # the message's own shape check names the tensor first; the rest as a file's
        said = {"'4.bias' has shape (7,)": "'policy_state.4.bias' has shape [7]",
                "'0.bias' is missing": "missing tensor(s) policy_state.0.bias",
                "obs_mean must be obs_dim=8": "'obs_mean' has shape [3]"}.get(expected, expected)
        assert policy is None and problem.reason == "bad weights" and said in problem, problem


def test_a_state_the_policy_fails_on_is_refused_and_the_next_one_answered():
    from offline_rl_core.serving.actor import Actor
    from offline_rl_core.serving.policy import LoadedPolicy

    policy = LoadedPolicy(_checkpoint())
    actor = Actor(policy)
    obs = np.zeros(8, np.float32)
    action, problem = actor.answer(obs, stamp=1)
    assert problem is None and action.shape == (2,) and np.all(np.abs(action) <= 1)
    action, problem = actor.answer(np.zeros(5, np.float32), stamp=2)  # the policy raises on this one
    assert action is None and problem.reason == "policy error" and "expects 8" in problem
    policy._b[2] = np.full(2, np.nan, np.float32)
    action, problem = actor.answer(obs, stamp=3)
    assert action is None and problem.reason == "non-finite action"


def test_a_message_is_stamped_with_the_sim_time_of_its_publication_not_of_its_callback():
    """A recorder on sim time that takes a command after the /clock of the step the command
    caused (or gets it from DDS after that /clock) still stamps it in its own tick, ordered by
    publication within it; a message waits until a later /clock says which tick it was in."""
    from offline_rl_core.nodes.publication_clock import ORDER_SPAN_NS, PublicationClock

    tick = 50_000_000
    clock = PublicationClock(kept=3)
    assert clock.add(1_000, "early") == [] and clock.stamp(1_000) is None  # before any /clock
    assert clock.add_clock(10_000_000, 7 * tick) == [(7 * tick, "early")]  # released, stamped by the first
    assert clock.add(13_000_500, "state 8") == []  # published after the newest /clock: waits
    assert clock.add(12_000_000, "command 7") == []  # taken late, published before state 8's /clock
    released = clock.add_clock(13_000_000, 8 * tick)  # the /clock the command caused
    assert [item for _, item in released] == ["command 7"]
    assert 7 * tick < released[0][0] < 7 * tick + ORDER_SPAN_NS  # in state 7's tick: the join pairs them
    assert clock.stamp(10_002_000) == 7 * tick + 2  # a nanosecond per microsecond since that /clock
    assert clock.stamp(13_000_000 + 10**12) == 8 * tick + ORDER_SPAN_NS  # never into the next tick
    assert clock.flush() == [(8 * tick, "state 8")]  # the recording ends: by the newest /clock
    clock.add_clock(20_000_000, 9 * tick)
    clock.add_clock(30_000_000, 10 * tick)  # three kept: state 7's is gone
    assert clock.stamp(11_000_000) == 8 * tick  # older than every /clock kept: the oldest
    nothing = PublicationClock()
    nothing.add(5, "a")
    assert nothing.flush() == [(None, "a")]  # no /clock ever came: the recorder uses the wall clock


def test_a_state_taken_before_its_clock_is_not_flushed_into_the_tick_before():
    """The learner flushes what waits once the stream falls quiet (a lockstep sim waiting for
    it). A state taken before the /clock published just before it (DDS delivers different
    writers in no order; a busy learner can pause between the two) must not be stamped by
    the tick before: its step would lose its next state, and the lockstep session would wait
    for that step forever."""
    from offline_rl_core.nodes.publication_clock import ORDER_SPAN_NS, PublicationClock

    tick = 50_000_000
    clock = PublicationClock()
    clock.add_clock(10_000_000, 7 * tick)
    assert clock.add(10_000_400, "state 7", sim_ns=7 * tick) == [] and not clock.clock_behind
    assert clock.add(12_000_000, "command 7") == []  # no sim time of its own: never held for it
    assert clock.add(13_000_500, "state 8", sim_ns=8 * tick) == []  # its /clock not taken yet
    assert clock.clock_behind
    assert clock.flush(wait_for_clock=True) == []  # held, all of it: nothing out of order
    assert [item for _, item in clock.add_clock(13_000_000, 8 * tick)] == ["state 7", "command 7"]
    assert not clock.clock_behind
    [(stamp, item)] = clock.flush(wait_for_clock=True)
    assert item == "state 8" and 8 * tick <= stamp < 8 * tick + ORDER_SPAN_NS  # in its own tick
    clock.add(20_000_000, "state 9", sim_ns=9 * tick)  # its /clock lost for good: an unheld flush
    clock.add(20_000_300, "command 9")
    assert clock.flush() == [(9 * tick, "state 9"), (9 * tick, "command 9")]  # never before the tick it says
