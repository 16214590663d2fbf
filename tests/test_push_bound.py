"""bench/push_bound.py writes its task variants by editing pusher_push as first shipped (the
wave, bench/push_tasks/pusher_push_wave.yaml): each variant must still apply to that file, load
as a valid task, change what it says it changes (and nothing the others change), and leave an
expert that pushes the puck home; the shipped pusher_push is the variant its figures chose. Its
DAgger rounds label every state the policy visits and count the budget in environment steps."""

from __future__ import annotations

import pytest
from bench_scripts import bench_script

from offline_rl_core.task.envs import expert_action, make_env
from offline_rl_core.task.pusher_push import PushSettings
from offline_rl_core.task.spec import load_task


@pytest.fixture(scope="module")
def push_bound():
    return bench_script("push_bound")


def test_each_variant_is_the_first_task_with_its_own_change(push_bound, tmp_path):
    shipped = load_task(push_bound.variant_task("wave", tmp_path))
    assert shipped.digest == "f371e75b24e83718"  # the first pusher_push: its figures keep their task file
    assert push_bound.variant_task("pusher_push", tmp_path) == "pusher_push"
    tasks = {name: load_task(push_bound.variant_task(name, tmp_path)) for name in push_bound.VARIANTS}
    assert len({t.digest for t in tasks.values()} | {shipped.digest}) == len(tasks) + 1
    for name, task in tasks.items():
        directions, frame = "direction" in name, "frame" in name
        # the elbow seen from the puck and along its line to the goal; the puck and the goal on the table
        extra = 4 if "elbow" in name or "table" in name else 0
        assert task.obs_dim == shipped.obs_dim + (4 if directions else 0) + (2 if frame else 0) + extra, name
        assert any(f.kind == "along_across" for f in task.observation) == frame, name
        assert task.control_period == (0.05 if "rate20" in name else shipped.control_period), name
        # the same 3 s per episode at either rate
        assert task.episodes.max_steps * task.control_period == pytest.approx(
            shipped.episodes.max_steps * shipped.control_period), name
        assert task.reward.success_within == shipped.reward.success_within, name
        assert PushSettings.of(task).approach == ("orbit" if name.startswith("orbit") else "wave"), name


def test_the_shipped_task_is_the_orbit_variant_at_20_hz_with_the_frame_features(push_bound, tmp_path):
    """What the push figures measured on ``orbit_direction_frame_rate20`` (the online stage's
    0.91 over ROS) were measured on: the shipped task but for its name, and so its digest."""
    def without_name(task):
        return {k: v for k, v in task.describe().items() if k != "name"}

    variant = load_task(push_bound.variant_task("orbit_direction_frame_rate20", tmp_path))
    shipped = load_task("pusher_push")
    assert without_name(variant) == without_name(shipped) and variant.digest != shipped.digest


def test_the_expert_pushes_the_puck_home_at_20_hz(push_bound, tmp_path):
    env = make_env(load_task(push_bound.variant_task("rate20", tmp_path)))
    for seed in (500000, 500001, 500002):
        env.reset(seed)
        done = False
        while not done:
            _, _, done, info = env.step(expert_action(env))
        assert info["success"], seed


def test_an_unknown_variant_is_refused_by_name(push_bound, tmp_path):
    with pytest.raises(SystemExit, match="unknown variant 'bigger'"):
        push_bound.variant_task("bigger", tmp_path)


def test_dagger_labels_every_state_of_every_round_and_counts_the_steps(push_bound, tmp_path):
    import argparse

    task = load_task(push_bound.variant_task("rate20", tmp_path))
    args = argparse.Namespace(dagger=2, dagger_demos=1, dagger_round_steps=120, dagger_steps=20, eval_episodes=2)
    run = push_bound.dagger(task, 16, args)
    steps = task.episodes.max_steps  # 60: two episodes a round
    assert run["episodes_per_round"] == 2 and run["labels"] == steps * (1 + 2 * 2)
    assert [p["round"] for p in run["curve"]] == [0, 2]
    assert [p["env_steps"] for p in run["curve"]] == [steps, steps * 5]
    assert all(0.0 <= p["success"] <= 1.0 for p in run["curve"]) and run["task_digest"] == task.digest


def test_a_stage_run_is_keyed_by_the_settings_it_was_given_each_flag_once(push_bound):
    import argparse

    given = dict(patience=1, hold_steps=60, grace_steps=None, bc_weight=10.0, seed=None, no_explore=None,
                 action_labels=None, stage_width=512)
    args = argparse.Namespace(**given)
    options = push_bound.stage_options(args)
    flags = [w for w in options if w.startswith("--")]
    assert len(flags) == len(set(flags)) and options[options.index("--bc-weight") + 1] == "10.0"
    assert "--stage-width" not in options  # not a flag of hil: the prior it names is trained that wide
    key = push_bound.online_key("orbit_direction_frame_rate20", args)
    assert key == "orbit_direction_frame_rate20/patience_1_hold-steps_60_bc-weight_10.0_stage-width_512"
    plain = argparse.Namespace(**{k: None for k in given})
    assert push_bound.online_key("rate20", plain) == "rate20"
    mean_only = argparse.Namespace(**{**given, "no_explore": True, "bc_weight": None})
    assert push_bound.stage_options(mean_only)[-1] == "--no-explore"  # a switch: the flag alone, no value
    assert push_bound.online_key("rate20", mean_only) == "rate20/patience_1_hold-steps_60_no-explore_stage-width_512"
    labelled = argparse.Namespace(**{**given, "action_labels": True, "bc_weight": None})
    assert push_bound.online_key("rate20", labelled) == "rate20/patience_1_hold-steps_60_action-labels_stage-width_512"
    over_ros = argparse.Namespace(**{**given, "action_labels": True, "bc_weight": None, "over_ros": True})
    assert push_bound.online_key("rate20", over_ros).endswith("_action-labels_stage-width_512_over-ros")
    assert "--over-ros" not in push_bound.stage_options(over_ros)  # push_bound's: hil runs --from-topics
