"""The nodes' checks of bad input, without DDS: every fuzzed message gets the reason written
out for it in tests/fuzz_messages.py, stamps never wedge a pairing, rejections are counted
by a fixed set of reasons and warned about at a throttled rate."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fuzz_messages import (JOINT_KINDS, POINT_KINDS, TRANSITION_KINDS, WEIGHTS_KINDS, broken_weights,
                           command_case, joint_case, point_case, stride0_checkpoint, transition_case, weights_case)
from offline_rl_core.nodes.joint_messages import action_from_effort, joints_from_state, point_xy
from offline_rl_core.nodes.pairing import NS_PER_S, StampOrder, StatePairing, check_answer_stamp, check_stamp
from offline_rl_core.common.rejections import REASONS, Rejection, RejectionCounter

N = 2000  # cases per message type
TICK = NS_PER_S // 50


def _reason(rejection):
    return None if rejection is None else rejection.reason


def test_fuzzed_states_and_points_get_the_reason_written_for_them():
    rng = np.random.default_rng(1)
    for _ in range(N):
        case = joint_case(rng, JOINT_KINDS[int(rng.integers(len(JOINT_KINDS)))], ("position", "velocity"), 3.0)
        f = case.fields
        joints, problem = joints_from_state(f["name"], f["position"], f["velocity"])
        problem = check_stamp(-1, 0) if f["bad_stamp"] else problem
        assert _reason(problem) == case.expect, (case, problem)
        if problem is None:  # the arm's joints, in its order, whatever order the message had
            named = dict(zip(f["name"] or ["shoulder", "elbow"], zip(f["position"], f["velocity"])))
            assert joints[0].tolist() == [named["shoulder"][0], named["elbow"][0]]
            assert joints[1].tolist() == [named["shoulder"][1], named["elbow"][1]]
        point = point_case(rng, POINT_KINDS[int(rng.integers(len(POINT_KINDS)))])
        xy, problem = point_xy(*point.fields["xy"])
        problem = check_stamp(0, 2 * NS_PER_S) if point.fields["bad_stamp"] else problem
        assert _reason(problem) == point.expect, point


def test_fuzzed_commands_are_refused_or_clipped_into_the_action_range():
    rng = np.random.default_rng(2)
    for _ in range(N):
        allow_empty = bool(rng.integers(2))
        case = command_case(rng, JOINT_KINDS[int(rng.integers(len(JOINT_KINDS)))], allow_empty)
        if case.fields["bad_stamp"]:
            continue  # a stamp is judged by the node (check_stamp), not with the effort
        action, problem = action_from_effort(case.fields["name"], case.fields["effort"], allow_empty)
        assert _reason(problem) == case.expect, case
        if action is not None:
            assert action.dtype == np.float32 and np.all(np.abs(action) <= 1.0)


def test_fuzzed_transitions_are_refused_for_their_reason_and_good_ones_kept():
    from offline_rl_core.data.bag.cdr import TransitionDecodeError, decode_transition_payloads
    from offline_rl_core.data.collect import collect_transitions
    from offline_rl_core.nodes.learner_service import check_row

    rows = collect_transitions(2, 0.5, 0).to_rows()
    rng = np.random.default_rng(3)
    for _ in range(N):
        case = transition_case(rng, TRANSITION_KINDS[int(rng.integers(len(TRANSITION_KINDS)))], rows)
        raw = case.fields.get("raw")
        if raw is None:
            raw = _cdr_float32_multiarray(case.fields["data"], case.fields["layout"])[:case.fields.get("truncate")]
        try:
            problem = check_row(decode_transition_payloads([raw])[0])
        except TransitionDecodeError:
            problem = Rejection("bad layout", "")
        assert _reason(problem) == case.expect, case


def _cdr_float32_multiarray(data, layout) -> bytes:
    """A std_msgs/Float32MultiArray serialized by rosbags' typestore (as a publisher sends it)."""
    from offline_rl_core.data.bag import typestore

    ts = typestore()
    Dim = ts.types["std_msgs/msg/MultiArrayDimension"]
    msg = ts.types["std_msgs/msg/Float32MultiArray"](
        layout=ts.types["std_msgs/msg/MultiArrayLayout"](dim=[Dim(label=lb, size=n, stride=n) for lb, n in layout],
                                                         data_offset=0),
        data=np.asarray(data, np.float32))
    return bytes(ts.serialize_cdr(msg, "std_msgs/msg/Float32MultiArray"))


def _weights_checkpoint(hidden: int = 32) -> dict:
    from offline_rl_core.serving.policy import policy_sequential

    net = policy_sequential(8, hidden, 2)
    return {"format": "pusher-rl/policy", "version": 1, "algorithm": "sac", "obs_dim": 8, "act_dim": 2,
            "hidden": hidden, "policy_state": dict(net.state_dict()), "weights_version": 1}


def test_fuzzed_weights_messages_never_load():
    from offline_rl_core.serving.signing import Signer
    from offline_rl_core.serving.weights import encode_weights, policy_from_weights_message

    signer = Signer.generate()
    verifier = signer.verifier()
    good_ckpt = _weights_checkpoint()
    good, broken = encode_weights(good_ckpt, signer), broken_weights(good_ckpt, signer)
    policy, problem = policy_from_weights_message("pusher-rl/weights", good, verifier, "w")
    assert problem is None and policy.weights_version == 1
    rng = np.random.default_rng(4)
    seen = set()
    for _ in range(600):
        case = weights_case(rng, WEIGHTS_KINDS[int(rng.integers(len(WEIGHTS_KINDS)))], good, broken)
        policy, problem = policy_from_weights_message(case.fields["label"] or "", case.fields["data"], verifier, "w")
        assert _reason(problem) == case.expect, (case.kind, problem)
        assert (policy is None) == (case.expect is not None)
        seen.add(case.kind)
    assert seen == set(WEIGHTS_KINDS)


def test_a_rogue_weights_message_is_refused_before_anything_is_allocated():
    """The review's two messages: the project's own encoder with a key of its own (version
    2**62, a saturating bias), and a 2 KB torch file whose layer is a stride-0 view of 8192².
    Neither acts, neither grows the process by more than a few MiB, the policy acting goes on."""
    import resource

    import torch

    from offline_rl_core.serving.actor import Actor
    from offline_rl_core.serving.policy import LoadedPolicy
    from offline_rl_core.serving.signing import Signer
    from offline_rl_core.serving.weights import encode_weights, policy_from_weights_message

    session = Signer.generate()
    ckpt = _weights_checkpoint()
    actor = Actor(LoadedPolicy(ckpt))
    rogue = {**ckpt, "weights_version": 2**62, "policy_state": {**ckpt["policy_state"]}}
    rogue["policy_state"]["4.bias"] = torch.full((2,), 1e6)
    messages = {"rogue": encode_weights(rogue, Signer.generate()), "stride-0": stride0_checkpoint(8192)}
    assert len(messages["stride-0"]) < 4096
    peak_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB
    for name, data in messages.items():
        for _ in range(50):
            policy, problem = policy_from_weights_message("pusher-rl/weights", data, session.verifier(),
                                                          "learner/weights")
            assert policy is None and problem.reason == "unsigned weights", (name, problem)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak_before < 50 * 1024
    obs = np.linspace(-1, 1, 8, dtype=np.float32)
    assert actor.version == 1 and np.array_equal(actor.act(obs), LoadedPolicy(ckpt).act(obs))


def test_weights_past_the_next_few_versions_or_unversioned_never_act():
    """Even signed, weights only move the acting version forward by a few: a version far
    ahead would make every later one of the real learner look old."""
    from offline_rl_core.serving.actor import MAX_VERSION_STEP, Actor
    from offline_rl_core.serving.policy import LoadedPolicy

    ckpt = _weights_checkpoint()
    unversioned = {k: v for k, v in ckpt.items() if k != "weights_version"}
    actor = Actor(LoadedPolicy(unversioned))  # started from a trained checkpoint file
    assert actor.offer_weights(LoadedPolicy(unversioned))[1].reason == "weights version"
    assert actor.offer_weights(LoadedPolicy({**ckpt, "weights_version": 40})) == (True, None)  # a late start
    assert actor.offer_weights(LoadedPolicy({**ckpt, "weights_version": 40})) == (False, None)  # seen
    assert actor.offer_weights(LoadedPolicy({**ckpt, "weights_version": 39})) == (False, None)  # older
    far = actor.offer_weights(LoadedPolicy({**ckpt, "weights_version": 41 + MAX_VERSION_STEP}))
    assert far[0] is False and far[1].reason == "weights version" and actor.version == 40
    assert actor.offer_weights(LoadedPolicy({**ckpt, "weights_version": 40 + MAX_VERSION_STEP})) == (True, None)
    assert actor.version == 40 + MAX_VERSION_STEP


def test_a_weights_message_is_checked_for_size_and_shape_before_its_tensors_are_read():
    """Signed by the session's key and still wrong: a header that claims more than the
    payload holds, a shape that is not its layer's, a tensor named twice, an absurd width."""
    import json
    import struct

    from offline_rl_core.serving.signing import Signer
    from offline_rl_core.serving.weights import MAGIC, decode_weights, encode_weights, WeightsRefused

    signer = Signer.generate()
    good = encode_weights(_weights_checkpoint(), signer)
    (length,) = struct.unpack("<I", good[len(MAGIC):len(MAGIC) + 4])
    start = len(MAGIC) + 4
    header, payload = json.loads(good[start:start + length]), good[start + length:-64]

    def resigned(change, cut=0) -> bytes:
        h = json.loads(json.dumps(header))
        change(h)
        text = json.dumps(h).encode()
        body = MAGIC + struct.pack("<I", len(text)) + text + payload[:len(payload) - cut]
        return body + signer.sign(body)

    cases = {
        "the tensors need": resigned(lambda h: None, cut=4),  # a payload short of its shapes
        "has shape [32, 9]": resigned(lambda h: h["tensors"][0].__setitem__(1, [32, 9])),
        "unexpected or repeated tensor": resigned(lambda h: h["tensors"].append(h["tensors"][0])),
        "hidden 100000 outside": resigned(lambda h: h["fields"].__setitem__("hidden", 100000)),
        "unversioned weights are refused": resigned(lambda h: h["fields"].pop("weights_version")),
        "signed for another session": resigned(lambda h: h.__setitem__("session", "0" * 32)),
        "expected an integer": resigned(lambda h: h["fields"].__setitem__("weights_version", True)),
    }
    for expected, data in cases.items():
        with pytest.raises(WeightsRefused) as refused:
            decode_weights(data, signer.verifier(), "w")
        assert expected in str(refused.value), (expected, str(refused.value))


# ------------------------------------------------------------------ stamps
def test_bad_stamps_and_lockstep_answers():
    assert check_stamp(0, 0) is None and check_stamp(1_700_000_000, NS_PER_S - 1) is None
    assert check_stamp(-1, 0).reason == check_stamp(5, NS_PER_S).reason == "bad stamp"
    assert check_answer_stamp(10, 10) is None
    assert check_answer_stamp(9, 10).reason == "stale stamp" and check_answer_stamp(11, 10).reason == "future stamp"


def test_stamp_order_refuses_stale_and_far_future_stamps_and_follows_a_confirmed_jump():
    order = StampOrder(jump_s=5.0)
    assert order.check(100 * NS_PER_S) is None
    assert order.check(100 * NS_PER_S) is None  # the same state again (a republish)
    assert order.check(100 * NS_PER_S + TICK) is None
    assert order.check(100 * NS_PER_S).reason == "stale stamp"
    assert order.check(10_000 * NS_PER_S).reason == "future stamp"
    assert order.check(100 * NS_PER_S + 2 * TICK) is None  # the stray ones moved nothing
    # a restarted source: its clock went back; the next state confirms it
    assert order.check(50 * NS_PER_S).reason == "stale stamp"
    assert order.check(50 * NS_PER_S) is None and order.newest == 50 * NS_PER_S
    assert order.check(50 * NS_PER_S + TICK) is None


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(min_value=0, max_value=2**62), max_size=20), st.integers(0, 2**40),
       st.lists(st.sampled_from([0, 1, 2, 250]), min_size=1, max_size=10))
def test_no_garbage_stamps_wedge_a_real_stream(garbage, start, steps):
    """After any burst of stray stamps, a real stream (whose states come again until answered,
    like the lockstep sim's) is followed again by its second state at the latest."""
    order = StampOrder(jump_s=5.0)
    real = start * TICK
    assert order.check(real) is None
    for g in garbage:
        order.check(g)
    refused = 0
    for step in steps:
        real += step * TICK
        if order.check(real) is not None:
            refused += 1
            assert order.check(real) is None  # its republish is taken
    assert refused <= 1


def test_pairing_keeps_targets_by_stamp_so_strays_displace_nothing():
    p = StatePairing()
    p.on_target(1, (0.1, 0.2))
    assert p.on_state(1, "s1").state == "s1"  # co-stamped from now on
    p.on_target(2, (0.3, 0.4))
    p.on_target(999, (9.0, 9.0))  # a stray target with a wild stamp
    p.on_target(1, (5.0, 5.0))  # and a late one for an old state
    done = p.on_state(2, "s2")
    assert done.state == "s2" and done.target_xy.tolist() == [0.3, 0.4]
    for stamp in range(1000, 1100):  # many strays: only the last KEEP are remembered
        p.on_target(stamp, (0.0, 0.0))
    assert len(p.goal.by_stamp) <= 32


# ------------------------------------------------------------------ counting and warning
def test_rejections_are_counted_by_a_fixed_set_of_reasons_and_warned_about_throttled():
    now = [0.0]
    counter = RejectionCounter(throttle_s=2.0, clock=lambda: now[0])
    nan, stale = Rejection("non-finite", "effort is not finite"), Rejection("stale stamp", "old")
    first = counter.reject("pusher/command", nan)
    assert first == "ignoring pusher/command: effort is not finite (non-finite: 1 so far)"
    assert counter.reject("pusher/state", stale) is not None  # another reason warns at once
    for _ in range(999):
        now[0] += 0.001
        assert counter.reject("pusher/command", nan) is None
    now[0] += 2.0
    assert counter.reject("pusher/command", nan).endswith("(non-finite: 1001 so far, 999 not shown)")
    assert counter.counts == {"non-finite": 1001, "stale stamp": 1} and counter.total == 1002
    with pytest.raises(ValueError, match="unknown rejection reason"):
        Rejection("weird", "x")
    assert set(REASONS) >= {"non-finite", "bad layout"}  # the learner's keys, as before
