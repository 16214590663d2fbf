"""Recording over ROS equals `offline-rl collect`; an interrupted recording is a readable bag."""

from __future__ import annotations

import re
import signal
import time

import numpy as np
import pytest

from offline_rl_core.bag import read_transitions
from offline_rl_core.collect import collect_transitions

from ros_helpers import ros2, ros_env, spawn  # noqa: F401 - fixtures

pytestmark = pytest.mark.ros


def lockstep_sim(spawn, seed: int, episodes: int = 0):
    return spawn(
        ros2("run", "sim", "node", "--ros-args", "-p", "mode:=lockstep", "-p", f"seed:={seed}", "-p", f"episodes:={episodes}"),
        "sim",
    )


def test_recording_is_bit_identical_to_collect(spawn, tmp_path):
    bag = tmp_path / "mix.db3"
    sim = lockstep_sim(spawn, seed=7, episodes=4)
    recorder = spawn(
        ros2("run", "recorder", "node", "--out", bag, "--episodes", 4, "--expert-frac", 0.5, "--seed", 7), "recorder"
    )
    assert recorder.wait(timeout=90) == 0, recorder.output()
    assert sim.wait(timeout=30) == 0, sim.output()  # the sim exits by itself after its episodes
    assert "wrote 400 transitions (4 episodes" in recorder.output()

    recorded = read_transitions(bag)
    reference = collect_transitions(4, 0.5, 7)
    assert np.array_equal(recorded.to_rows(), reference.to_rows())
    assert list(np.unique(recorded.source)) == [0, 1]


@pytest.mark.slow
@pytest.mark.parametrize("sig, name", [(signal.SIGINT, "cut.db3"), (signal.SIGTERM, "cut.mcap")])
def test_interrupted_recording_leaves_a_readable_bag(spawn, tmp_path, sig, name):
    bag = tmp_path / name
    lockstep_sim(spawn, seed=3)
    recorder = spawn(
        ros2("run", "recorder", "node", "--out", bag, "--episodes", 1000, "--expert-frac", 0.5, "--seed", 3), "recorder"
    )
    assert recorder.wait_for_output("recording 1000 episodes", timeout=30), recorder.output()
    time.sleep(2.0)  # mid-episode somewhere
    rc = recorder.stop(sig, timeout=20)
    assert rc == 0, f"exit {rc}: {recorder.output()}"
    match = re.search(r"interrupted; wrote (\d+) transitions", recorder.output())
    assert match, recorder.output()
    n = int(match.group(1))
    assert n > 0
    recorded = read_transitions(bag)
    assert len(recorded) == n  # every transition received is in the bag
    # 1000 episodes at expert-frac 0.5: all expert so far, so the prefix matches collect.
    episodes = int(recorded.episode.max()) + 1
    reference = collect_transitions(episodes, 1.0, 3)
    assert np.array_equal(recorded.to_rows(), reference.to_rows()[:n])
