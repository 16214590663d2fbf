"""Nothing trained on while the e-stop was engaged, offline too: a session bag holding the
``estop`` topic (and, where recorded, the reset service's events) is read by ``offline-rl
train`` and the learner without the transitions recorded while it was engaged."""

from __future__ import annotations

import json

import numpy as np
import pytest

from offline_rl_core.data.bag import BagWriter, encode_transition_rows, typestore
from offline_rl_core.data.bag.cdr import TRANSITION_MSGTYPE, TRANSITION_TOPIC
from offline_rl_core.data.bag.estop_spans import (
    RESET_EVENT_MSGTYPE, RESET_EVENT_TOPIC, RESPONSE_SENT, engaged_spans, event_typestore,
)
from offline_rl_core.data.transitions import PUSHER_LAYOUT, Transitions

T0, PERIOD = 1_735_689_600 * 10**9, 20_000_000
N = 60


def _rows() -> np.ndarray:
    """N transitions of two episodes; row i has reward -i, so the rows read back name themselves."""
    rng = np.random.default_rng(0)
    data = Transitions.empty(N, PUSHER_LAYOUT)
    data.obs[:] = rng.uniform(-1, 1, data.obs.shape)
    data.next_obs[:] = rng.uniform(-1, 1, data.next_obs.shape)
    data.action[:] = rng.uniform(-1, 1, data.action.shape)
    data.reward[:] = -np.arange(N, dtype=np.float32)
    data.episode[:] = np.arange(N) // 30
    data.step[:] = np.arange(N) % 30
    data.truncated[:] = data.step == 29
    data.terminated[:] = False
    data.success[:] = False
    data.source[:] = 0
    return data.to_rows()


def _bool(value: bool) -> bytes:
    store = typestore()
    return bytes(store.serialize_cdr(store.types["std_msgs/msg/Bool"](data=value), "std_msgs/msg/Bool"))


def _reset_answer(success: bool) -> bytes:
    store = event_typestore()
    info = store.types["service_msgs/msg/ServiceEventInfo"](
        event_type=RESPONSE_SENT, stamp=store.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
        client_gid=np.zeros(16, dtype=np.uint8), sequence_number=1)
    answer = store.types["std_srvs/msg/Trigger_Response"](success=success, message="")
    event = store.types[RESET_EVENT_MSGTYPE](info=info, request=[], response=[answer])
    return bytes(store.serialize_cdr(event, RESET_EVENT_MSGTYPE))


def _session_bag(path, estop: list[tuple[int, bool]], resets: list[tuple[int, bool]] | None = None):
    """Transition i stamped T0 + i periods; estop words and reset answers at the rows' indices."""
    with BagWriter(path) as bag:
        bag.add_topic(TRANSITION_TOPIC, TRANSITION_MSGTYPE)
        bag.add_topic("/estop", "std_msgs/msg/Bool")
        if resets is not None:
            store = event_typestore()
            bag.add_topic(RESET_EVENT_TOPIC, RESET_EVENT_MSGTYPE,
                          msgdef=store.generate_msgdef(RESET_EVENT_MSGTYPE, ros_version=2)[0],
                          rihs01=store.hash_rihs01(RESET_EVENT_MSGTYPE))
        for i, payload in enumerate(encode_transition_rows(_rows())):
            bag.write(TRANSITION_TOPIC, T0 + i * PERIOD, payload)
        for at, value in estop:
            bag.write("/estop", T0 + at * PERIOD - 1, _bool(value))  # just before row `at`
        for at, success in resets or ():
            bag.write(RESET_EVENT_TOPIC, T0 + at * PERIOD - 1, _reset_answer(success))
    return path


def _kept(data: Transitions) -> list[int]:
    return sorted(int(-r) for r in data.reward)


@pytest.mark.parametrize("name", ["session.db3", "session.mcap"])
def test_train_reads_only_the_rows_outside_the_engaged_span(tmp_path, capsys, name):
    from offline_rl_core.commands.cli import main
    from offline_rl_core.runs.training_run import load_bags

    bag = _session_bag(tmp_path / name, [(10, True), (20, False)])  # no reset recorded: the false releases
    data, summary = load_bags([str(bag)])
    assert _kept(data) == [i for i in range(N) if not 10 <= i < 20]
    assert summary[0]["estop_dropped"] == 10 and summary[0]["transitions"] == N - 10

    out = tmp_path / "run"
    assert main(["train", "--bag", str(bag), "--algo", "bc", "--steps", "2", "--batch-size", "8", "--hidden", "8",
                 "--eval-episodes", "0", "--out", str(out)]) == 0
    assert "left out 10 transitions recorded while the e-stop was engaged" in capsys.readouterr().err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["estop_dropped"] == 10 and metrics["transitions"] == N - 10


def test_the_recorded_reset_releases_not_the_false(tmp_path):
    from offline_rl_core.runs.training_run import load_bags

    # pressed at 10, let go at 20; a refused reset at 25, the one that succeeds at 30;
    # pressed again at 50 and never reset: engaged to the end
    bag = _session_bag(tmp_path / "s.db3", [(10, True), (20, False), (50, True)], resets=[(25, False), (30, True)])
    data, summary = load_bags([str(bag)])
    assert _kept(data) == [*range(10), *range(30, 50)]
    assert summary[0]["estop_dropped"] == 30


def test_a_reset_while_the_button_is_held_releases_nothing():
    assert engaged_spans([(10, True), (30, False)], resets=[20, 40]) == [(10, 40)]
    assert engaged_spans([(10, True), (15, True), (30, False)], resets=None) == [(10, 30)]
    assert engaged_spans([(10, False)], resets=None) == []


def test_a_session_stopped_the_whole_time_is_refused_in_one_line(tmp_path):
    from offline_rl_core.common.errors import UserError
    from offline_rl_core.runs.training_run import load_bags

    bag = _session_bag(tmp_path / "s.db3", [(0, True)])
    with pytest.raises(UserError, match="s.db3: every one of its 60 transitions was recorded while the e-stop"):
        load_bags([str(bag)])


def test_a_bag_without_an_estop_topic_keeps_its_summary(tmp_path):
    from offline_rl_core.data.bag import write_transitions
    from offline_rl_core.runs.training_run import load_bags

    bag = tmp_path / "plain.db3"
    write_transitions(bag, Transitions.from_rows(_rows(), PUSHER_LAYOUT))
    data, summary = load_bags([str(bag)])
    assert len(data) == N and "estop_dropped" not in summary[0]


def test_the_learners_offline_half_leaves_out_the_engaged_rows(tmp_path):
    from offline_rl_core.learners import TrainConfig
    from offline_rl_core.nodes.learner_service import LearnerService, LearnerServiceConfig

    bag = _session_bag(tmp_path / "session.db3", [(10, True), (20, False)])
    lines = []
    service = LearnerService(LearnerServiceConfig(bags=[str(bag)], out=str(tmp_path / "learner"), seed=0,
                                                  train=TrainConfig(algo="sac", batch_size=8, hidden=8)),
                             log=lines.append)
    assert service.learner.n_offline == N - 10 and service.status()["offline_estop_dropped"] == 10
    assert "offline half: left out 10 transitions recorded while the e-stop was engaged" in lines


def test_transitions_joined_from_raw_topics_leave_out_the_engaged_states(tmp_path):
    from raw_topic_bags import START_NS, TICK_NS, record_raw_bag

    from offline_rl_core.runs.training_run import load_bags

    spec = "pusher_reach"  # the task file says how its raw topics join
    plain, stopped = tmp_path / "plain.db3", tmp_path / "stopped.db3"
    record_raw_bag(plain, episodes=1, expert_frac=1.0, seed=3, sim_like=False)
    # pressed just before the state of step 10, released just before step 30's
    record_raw_bag(stopped, episodes=1, expert_frac=1.0, seed=3, sim_like=False,
                   estop=((START_NS + 10 * TICK_NS - 1, True), (START_NS + 30 * TICK_NS - 1, False)))
    full, plain_summary = load_bags([str(plain)], from_topics=spec)
    kept, summary = load_bags([str(stopped)], from_topics=spec)
    assert "estop_dropped" not in plain_summary[0] and "estop_dropped" not in plain_summary[0]["from_topics"]
    assert summary[0]["estop_dropped"] == 20 and summary[0]["from_topics"]["estop_dropped"] == 20
    rows = full.to_rows()
    assert np.array_equal(kept.to_rows(), np.concatenate([rows[:10], rows[30:]]))
