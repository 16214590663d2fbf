"""What a node's /diagnostics entry says, from its ~/status dict (no DDS; the ROS test is test_ros_viz)."""

from __future__ import annotations

from offline_rl_core.nodes.diagnostics import (
    ERROR, OK, STALE_WEIGHTS_S, WARN, StatusDiagnosis, flatten, learner_checks, policy_checks, recorder_checks,
)


def test_every_counter_becomes_a_key_value_named_by_its_path():
    values = dict(flatten({"answered": 5, "rejected": {"bad stamp": 2}, "messages": {"pusher/state": 7},
                           "weights_age_s": None, "intervening": False, "loss": 0.1234567891}))
    assert values == {"answered": "5", "rejected/bad stamp": "2", "messages/pusher/state": "7",
                      "weights_age_s": "none", "intervening": "false", "loss": "0.123457"}


def test_rejections_warn_only_while_new_ones_come():
    diagnosis = StatusDiagnosis(idle="serving")
    first = diagnosis.report({"rejected": {}})
    assert (first.level, first.message) == (OK, "serving")
    refused = diagnosis.report({"rejected": {"bad stamp": 2, "non-finite": 1}})
    assert refused.level == WARN
    assert refused.message == "3 messages refused since the last report (bad stamp: 2, non-finite: 1)"
    # the same totals a second later: nothing new was refused, the node is healthy again
    again = diagnosis.report({"rejected": {"bad stamp": 2, "non-finite": 1}})
    assert again.level == OK and ("rejected/bad stamp", "2") in again.values
    more = diagnosis.report({"rejected": {"bad stamp": 3, "non-finite": 1}})
    assert more.level == WARN and more.message.startswith("1 messages refused") and "bad stamp: 1" in more.message


def test_the_worst_problem_sets_the_level_and_comes_first():
    diagnosis = StatusDiagnosis(checks=(recorder_checks,))
    report = diagnosis.report({"flush_lag_s": 5.0, "flush_interval_s": 1.0, "low_space_bytes": 3 << 20,
                               "rejected": {}})
    assert report.level == ERROR
    assert report.message.startswith("recording stopped: 3 MiB free")
    assert "waiting 5.0 s for the disk" in report.message


def test_recorder_flush_lag_within_its_interval_is_healthy():
    report = StatusDiagnosis(checks=(recorder_checks,), idle="recording").report(
        {"flush_lag_s": 0.9, "flush_interval_s": 1.0, "low_space_bytes": None, "error": None})
    assert (report.level, report.message) == (OK, "recording")


def test_policy_on_old_weights_warns_and_a_checkpoint_file_has_no_age():
    old = policy_checks({"weights_age_s": STALE_WEIGHTS_S + 1, "weights_version": 4, "loads_dropped": {}})
    assert [level for level, _ in old] == [WARN] and "version 4" in old[0][1]
    assert policy_checks({"weights_age_s": None, "weights_version": 0, "loads_dropped": {"weights": 0}}) == []
    assert policy_checks({"weights_age_s": 1.0, "loads_dropped": {"weights": 2}})[0][0] == WARN


def test_learner_far_behind_warns():
    assert learner_checks({"owed": 5}) == []
    assert learner_checks({"owed": 10_000})[0][0] == WARN


def test_idle_message_can_read_the_status():
    report = StatusDiagnosis(idle=lambda s: f"episode {s['episode']}").report({"episode": 3})
    assert report.message == "episode 3" and report.values == [("episode", "3")]


def test_an_engaged_estop_is_an_error_and_a_tripped_watchdog_a_warning():
    from offline_rl_core.nodes.diagnostics import ERROR, OK, WARN, StatusDiagnosis

    diagnosis = StatusDiagnosis()
    calm = {"estop": {"engaged": False, "held": False, "engagements": 0}, "faults": {}}
    assert diagnosis.report(calm).level == OK
    tripped = {**calm, "faults": {"watchdog": {"trips": 2, "silent": True, "timeout_s": 0.06}}}
    report = diagnosis.report(tripped)
    assert report.level == WARN and "watchdog tripped 2 time(s)" in report.message
    stopped = {**tripped, "estop": {"engaged": True, "held": True, "engagements": 1}}
    report = diagnosis.report(stopped)
    assert report.level == ERROR and report.message.startswith("e-stop engaged")
