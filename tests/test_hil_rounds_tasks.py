"""The offline correction rounds (`offline-rl hil` without --online) on a task other than
pusher_reach: every node is given the task, the corrector takes over with the task's
expert, the corrections are recorded in the task's layout, the trainer retrains a
checkpoint of the task, and the served policy is scored in the task's own env."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from offline_rl_core.common.errors import UserError
from offline_rl_core.data.bag import write_transitions
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.data.fleet import read_fleet
from offline_rl_core.task.spec import load_task
from ros_helpers import REPO, ros_env, task_bag_and_prior  # noqa: F401 - fixtures


def test_several_bags_of_a_task_merge_in_its_layout_and_another_tasks_bag_is_refused(tmp_path):
    """What each round's retraining reads: the offline bag and every round's corrections, in
    the task's layout (not pusher_reach's); a bag of another layout among them is one line."""
    push = load_task("pusher_push")
    bags = []
    for seed in (0, 1):
        bags.append(tmp_path / f"push{seed}.db3")
        write_transitions(bags[-1], collect_transitions(1, 1.0, seed, task=push), task=push)
    data, _ = read_fleet([str(b) for b in bags], workers=1)
    assert (data.layout.obs_dim, data.layout.act_dim) == (push.obs_dim, push.act_dim)
    assert len(data) == 2 * push.episodes.max_steps and np.unique(data.episode).tolist() == [0, 1]
    write_transitions(tmp_path / "reach.db3", collect_transitions(1, 1.0, 0))
    with pytest.raises(UserError, match=r"reach.db3: its transitions \(obs 8, .*\) are not those of .*push0.db3"):
        read_fleet([str(bags[0]), str(tmp_path / "reach.db3")], workers=1)


@pytest.fixture(scope="module")
def push(tmp_path_factory):
    """A 4-episode pusher_push bag and a 50-step AWAC prior trained on it, narrower than the
    trainer's default (a prior's width is its own: an auto prior may be wider)."""
    return task_bag_and_prior(tmp_path_factory, "pusher_push", hidden=64)


@pytest.mark.ros
@pytest.mark.slow
def test_the_rounds_run_on_pusher_push(ros_env, tmp_path, push):
    """`hil --rounds 2 --episodes 2 --steps 50 --task pusher_push`: the sim hosts the push
    arm (the puck on its tracked-point topic), each round's bag holds pusher_push's
    transitions and records the task, each round's retrained checkpoint records it, and the
    summary's success is the served policy's on pusher_push's held-out resets."""
    from offline_rl_core.data.bag import read_transitions
    from offline_rl_core.data.task_record import recorded_task
    from offline_rl_core.evaluation.rollouts import evaluate_policy
    from offline_rl_core.pipelines.hil import EVAL_SEED
    from offline_rl_core.serving.checkpoint import load_checkpoint
    from offline_rl_core.serving.policy import load_policy

    task = load_task("pusher_push")
    bag, prior = push
    out = tmp_path / "hil"
    proc = subprocess.run([sys.executable, "-m", "offline_rl_core", "hil", "--task", "pusher_push", "--bag", str(bag),
                           "--prior", str(prior), "--rounds", "2", "--episodes", "2", "--steps", "50",
                           "--eval-episodes", "2", "--logger", "none", "--out", str(out)],
                          env=ros_env, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["config"]["task"] == "pusher_push"
    rows = summary["rounds"]
    assert [r["round"] for r in rows] == [1, 2]
    # the corrector heard the puck on its topic and took over with the push expert
    assert sum(r["correction_transitions"] for r in rows) > 0 and sum(r["takeovers"] for r in rows) > 0
    for r in rows:
        # every state was answered through the mux, the corrector heard each: the policy's own
        # command never reached the arm's controller topic first (the served node only answers)
        mux_log = (Path(r["bag"]).parent / "mux.log").read_text()
        forwarded = re.search(r"forwarded (\d+) policy and (\d+) human commands", mux_log)
        assert forwarded and int(forwarded[1]) + int(forwarded[2]) == r["transitions"], mux_log[-500:]
        assert f"answered {r['transitions']} states" in (Path(r["bag"]).parent / "corrector.log").read_text()
    for r in rows:
        data = read_transitions(r["bag"])
        assert recorded_task(r["bag"]).digest == task.digest
        assert (data.layout.obs_dim, data.layout.act_dim) == (task.obs_dim, task.act_dim)
        assert len(data) == r["transitions"] == 2 * task.episodes.max_steps and r["episodes"] == 2
        ckpt = load_checkpoint(r["checkpoint"])
        assert ckpt["task"]["digest"] == task.digest and (ckpt["obs_dim"], ckpt["act_dim"]) == (task.obs_dim,
                                                                                                task.act_dim)
        assert ckpt["hidden"] == 64  # retrained from the served checkpoint at its width
    # the served policy reloaded each round's checkpoint; the last one is scored in pusher_push's env
    assert (out / "policy.log").read_text().count("reloaded ") == 2
    ev = evaluate_policy(load_policy(out / "policy.pt", task), 2, EVAL_SEED, task=task)
    assert ev["success_rate"] == summary["final_success"]
