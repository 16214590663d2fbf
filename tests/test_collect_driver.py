"""The recorder's collection logic (offline_rl_core.nodes.collect_driver) against the sim's, without DDS."""

from __future__ import annotations

import numpy as np

from offline_rl_core.data.bag import encode_transition_rows, transition_ends_episode
from offline_rl_core.data.collect import EpisodePlan, collect_transitions
from offline_rl_core.nodes.collect_driver import CollectDriver
from offline_rl_core.nodes.sim_loop import SimLoop
from offline_rl_core.data.transitions import SOURCE_EXPERT, SOURCE_RANDOM


def _show(driver: CollectDriver, state) -> None:
    """Hand the driver a state and its target, as the recorder's subscriptions do."""
    assert driver.on_state(state.stamp_ns, state.position, state.velocity) is None
    driver.on_target(state.stamp_ns, state.target[:2])


def test_driving_a_lockstep_sim_records_what_collect_does():
    episodes, expert_frac, seed = 5, 0.4, 2
    sim = SimLoop("lockstep", seed=seed, episodes=episodes)
    driver = CollectDriver(episodes, EpisodePlan(episodes, expert_frac, seed))
    state, rows, sources = sim.start_episode(), [], []
    _show(driver, state)
    while not driver.finished:
        assert driver.ready()
        command = driver.next_command()
        assert command.stamp == state.stamp_ns and not driver.ready()  # one command per transition
        # The sim republishes the answered state (our command was lost): the same command
        # again, not a new draw.
        assert driver.on_state(state.stamp_ns, state.position, state.velocity) is command
        step = sim.command(command.stamp, command.action, command.source)
        message = encode_transition_rows(step.transition[None])[0]
        assert driver.on_transition(transition_ends_episode(message)) == step.episode_over
        rows.append(step.transition)
        sources.append(command.source)
        # A late copy of the answered state, its transition in: ignored.
        assert driver.on_state(state.stamp_ns, state.position, state.velocity) is None and not driver.ready()
        state = step.new_episode if step.episode_over else step.next_state
        if state is not None:
            _show(driver, state)
    expected = collect_transitions(episodes, expert_frac, seed)
    assert np.array_equal(np.array(rows), expected.to_rows())  # bit for bit, random actions included
    assert driver.episodes_done == episodes and driver.transitions == len(expected.obs)
    assert sources.count(SOURCE_EXPERT) == 2 * 100 and set(sources) == {SOURCE_EXPERT, SOURCE_RANDOM}


def test_a_state_is_answered_only_with_its_target_and_the_newest_wins():
    driver = CollectDriver(1, EpisodePlan(1, 1.0, 0))
    zeros = np.zeros(2)
    driver.on_state(10, zeros, zeros)
    driver.on_target(20, (0.1, 0.1))
    assert not driver.ready()  # a target of another state
    driver.on_state(20, zeros, zeros)
    assert driver.ready() and driver.next_command().stamp == 20
    assert driver.on_transition(True) and driver.finished


def test_recording_what_flows_counts_episodes_and_never_commands():
    driver = CollectDriver(2)  # no plan: passive
    driver.on_state(0, np.zeros(2), np.zeros(2))
    driver.on_target(0, (0.1, 0.1))
    assert not driver.ready()
    for ended in (False, True, True):
        driver.on_transition(ended)
    assert (driver.transitions, driver.episodes_done, driver.finished) == (3, 2, True)
    assert not CollectDriver(None).finished  # no episode count: until stopped
