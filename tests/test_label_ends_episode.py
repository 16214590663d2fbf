"""A person's label ends the episode it labels, in the sim's loop (no ROS): lockstep and realtime."""

from __future__ import annotations

import numpy as np
import pytest

from offline_rl_core.data.transitions import Transitions
from offline_rl_core.nodes.sim_loop import SimLoop
from offline_rl_core.task import features
from offline_rl_core.task.spec import load_task

ZERO = np.zeros(2, np.float32)


def lockstep_steps(loop: SimLoop, n: int) -> list:
    steps = []
    for _ in range(n):
        steps.append(loop.command(loop.current.stamp_ns, ZERO, 2))
    return steps


@pytest.mark.parametrize("task", ["pusher_reach", "pusher_push"])
def test_a_success_label_ends_the_current_episode_at_its_next_step_as_terminal(task):
    loop = SimLoop("lockstep", seed=3, episodes=3, task=task)
    loop.start_episode()
    lockstep_steps(loop, 5)
    assert loop.label(True) == (0, None)  # no episode given: the one of the last transition, the current one
    (step,) = lockstep_steps(loop, 1)
    last = Transitions.from_rows(step.transition[None], loop.layout)
    assert step.episode_over and step.next_state is None and step.new_episode is not None
    assert int(last.step[0]) == 5 and bool(last.terminated[0]) and not bool(last.truncated[0])
    assert bool(last.success[0])  # the person's word, whatever the simulator's
    # the same step unlabelled, and scored by the task's rule with the label as the state's success
    twin = SimLoop("lockstep", seed=3, episodes=3, task=task)
    twin.start_episode()
    lockstep_steps(twin, 5)
    success_before = bool(twin.env.success)
    (plain,) = lockstep_steps(twin, 1)
    assert not plain.episode_over
    same = ["obs", "action", "next_obs", "episode", "step", "source"]
    assert all(np.array_equal(step.transition[twin.layout.slices[k]], plain.transition[twin.layout.slices[k]])
               for k in same)
    env = twin.env
    vectors = {k: v[None] for k, v in env.vectors().items()}
    scored = features.score(twin.task, env.joint_positions[None], vectors, [env.steps], [success_before],
                            success_now=[True])
    assert last.reward[0] == np.float32(scored.reward[0])  # the task's bonus included
    assert loop.episode == 1 and loop.current.stamp_ns == loop.start_ns + loop.ticks_per_episode * loop.tick_ns
    # the next episode runs to its time limit: the label was of the one before
    steps = lockstep_steps(loop, load_task(task).episodes.max_steps)
    assert [s.episode_over for s in steps].index(True) == len(steps) - 1
    summary = loop.summary()
    assert summary["episodes"] == 2 and summary["labelled"] == 1
    truth = loop.results[0][0]  # the simulator's success stays the episode's result
    assert summary["labels_against_simulator"] == int(not truth)


def test_a_failure_label_truncates_and_overrides_a_latched_success():
    loop = SimLoop("lockstep", seed=0, episodes=1)  # pusher_reach latches success
    loop.start_episode()
    lockstep_steps(loop, 2)
    loop.env.success = True  # as if the fingertip had reached the target earlier
    loop.label(True)
    assert loop.label(False, episode=0) == (0, None)  # a later label replaces the earlier
    (step,) = lockstep_steps(loop, 1)
    last = Transitions.from_rows(step.transition[None], loop.layout)
    assert step.episode_over and loop.finished
    assert bool(last.truncated[0]) and not bool(last.terminated[0]) and not bool(last.success[0])
    assert loop.summary()["labelled"] == 1


def test_a_label_of_a_past_episode_ends_nothing_and_one_that_names_none_is_refused():
    loop = SimLoop("lockstep", seed=1, episodes=3)
    loop.start_episode()
    target, problem = loop.label(True)
    assert target is None and problem.reason == "bad label"  # before any step: which episode cannot be told
    assert loop.label(True, episode=1)[1].reason == "bad label"  # not yet begun
    lockstep_steps(loop, 3)
    loop.label(False)
    lockstep_steps(loop, 1)  # episode 0 ends here
    assert loop.episode == 1
    # pressed just after the end: the last transition was episode 0's, so it labels that one
    assert loop.label(True) == (0, None)
    assert loop.label(True, episode=0) == (0, None)
    steps = lockstep_steps(loop, loop.ticks_per_episode)
    assert [s.episode_over for s in steps].index(True) == len(steps) - 1  # episode 1 ran to its limit
    assert loop.summary()["labelled"] == 1


def test_a_label_ends_a_realtime_episode_at_its_next_tick():
    loop = SimLoop("realtime", seed=2)
    loop.start_episode()
    loop.hold(np.array([0.3, -0.3], np.float32), 3, None)
    ticks = [loop.tick() for _ in range(4)]
    assert not any(t.episode_over for t in ticks)
    assert loop.label(True) == (0, None)
    step = loop.tick()
    last = Transitions.from_rows(step.transition[None], loop.layout)
    assert step.episode_over and bool(last.terminated[0]) and int(last.step[0]) == 4 and int(last.source[0]) == 3
    nxt = loop.tick()
    assert int(Transitions.from_rows(nxt.transition[None], loop.layout).episode[0]) == 1 and not nxt.episode_over
    assert loop.summary()["labelled"] == 1


def test_a_raw_topic_session_records_the_labels_with_the_tasks_topics():
    from offline_rl_core.pipelines.hil_online import OnlineHilConfig, _record_topics

    args = _record_topics(OnlineHilConfig(task="pusher_push", from_topics=True)).split()
    topics = args[1:args.index("--types")]
    assert args[0] == "--topics" and "episode_label" in topics and "task_description" in topics


def test_a_step_budget_ends_the_run_however_its_episodes_end():
    """``steps``: the sim runs that many steps where episodes end early (on a label here): the
    step that reaches it ends its episode, truncated, and the run is finished."""
    loop = SimLoop("lockstep", seed=0, task="pusher_push", steps=7)
    loop.start_episode()
    lockstep_steps(loop, 2)
    loop.label(True)
    first = lockstep_steps(loop, 1)[0]
    assert first.episode_over and not loop.finished  # episode 0: 3 steps, the label's
    rest = lockstep_steps(loop, 4)
    assert [s.episode_over for s in rest] == [False, False, False, True]
    last = Transitions.from_rows(rest[-1].transition[None], loop.layout)
    assert bool(last.truncated[0]) and not bool(last.terminated[0]) and int(last.step[0]) == 3
    assert loop.finished and rest[-1].new_episode is None and loop.steps_taken == 7
    assert loop.summary()["episodes"] == 2
