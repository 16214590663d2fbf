"""The gamepad corrector's mapping and rule (no DDS; over ROS through the mux: test_ros_viz)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from offline_rl_core.common.errors import UserError
from offline_rl_core.nodes.gamepad import GamepadMapping, GamepadTeleop, label_json, load_mapping
from ros_helpers import REPO

CONFIG = REPO / "ros_ws" / "src" / "corrections" / "config"
XBOX_YAML = CONFIG / "gamepad_xbox.yaml"
PS_YAML = CONFIG / "gamepad_ps.yaml"
CARTESIAN_YAML = CONFIG / "gamepad_xbox_cartesian.yaml"


def joy(axes=None, pressed=()):
    """An Xbox pad's Joy message as the joy node sends it: 6 axes, 11 buttons."""
    a = [0.0] * 6
    for i, v in (axes or {}).items():
        a[i] = v
    return a, [1 if i in pressed else 0 for i in range(11)]


def test_the_shipped_xbox_file_is_the_built_in_default():
    assert load_mapping(XBOX_YAML) == GamepadMapping(source=str(XBOX_YAML))
    assert load_mapping("") == GamepadMapping()


def test_deadman_takes_over_and_sticks_give_the_action_in_joint_order():
    pad = GamepadTeleop(GamepadMapping(), act_dim=2)
    pad.on_joy(*joy({0: -0.5, 2: 0.25}))
    assert pad.decide() is None  # sticks alone: the policy keeps the arm
    pad.on_joy(*joy({0: -0.5, 2: 0.25}, pressed={9}))  # LB held
    np.testing.assert_array_equal(pad.decide(), np.array([0.5, -0.25], np.float32))
    pad.on_joy(*joy({0: -3.0, 2: 0.01}, pressed={9}))  # beyond the range, and inside the deadzone
    np.testing.assert_array_equal(pad.decide(), np.array([1.0, 0.0], np.float32))
    pad.on_joy(*joy({0: -0.5}))  # released
    assert pad.decide() is None


def test_a_seven_joint_arm_gets_zeros_past_the_mapped_axes():
    pad = GamepadTeleop(GamepadMapping(), act_dim=7)
    pad.on_joy(*joy({0: -1.0, 1: 0.5, 2: 1.0, 3: -0.5}, pressed={9}))
    np.testing.assert_array_equal(pad.decide(), np.array([1.0, -1.0, 0.5, -0.5, 0, 0, 0], np.float32))


def test_label_buttons_label_once_per_press():
    pad = GamepadTeleop(GamepadMapping(), act_dim=2)
    labels = []
    for pressed in ({0}, {0}, set(), {0}, {1}, {1, 9}):
        events, problem = pad.on_joy(*joy(pressed=pressed))
        assert problem is None
        labels += events.labels
    assert labels == ["success", "success", "failure"]
    assert json.loads(label_json("success")) == {"label": "success"}


def test_a_joy_message_the_mapping_cannot_read_is_refused_and_changes_nothing():
    pad = GamepadTeleop(GamepadMapping(), act_dim=2)
    pad.on_joy(*joy({0: -0.5}, pressed={9}))
    events, problem = pad.on_joy([0.0, 0.0], [0] * 11)
    assert events is None and problem.reason == "wrong length" and "axis 3" in problem
    events, problem = pad.on_joy([float("nan")] * 6, [0] * 11)
    assert problem.reason == "non-finite"
    _, problem = pad.on_joy([0.0] * 6, [1, 0])
    assert problem.reason == "wrong length" and "button 9" in problem
    np.testing.assert_array_equal(pad.decide(), np.array([0.5, 0.0], np.float32))  # still the last good one


def test_a_custom_mapping_file(tmp_path):
    path = tmp_path / "pad.yaml"
    path.write_text("deadman: 5\naxes: [{axis: 1, scale: 0.5}, null]\ndeadzone: 0\nsuccess: 2\nfailure: null\n")
    mapping = load_mapping(path)
    assert (mapping.deadman, mapping.axes, mapping.success, mapping.failure) == (5, ((1, 0.5), None), 2, None)
    pad = GamepadTeleop(mapping, act_dim=2)
    events, _ = pad.on_joy([0.0, 0.8, 0.9], [0, 0, 1, 0, 0, 1])
    np.testing.assert_array_equal(pad.decide(), np.array([0.4, 0.0], np.float32))
    assert events.labels == ["success"]


@pytest.mark.parametrize("text, error", [
    ("deadman: -1\n", "deadman: expected a button index"),
    ("axes: [{axis: 0, scale: .nan}]\n", r"axes\[0\].scale: expected a finite number"),
    ("axes: [{axs: 0}]\n", r"axes\[0\]: expected \{axis: INDEX, scale: S\}"),
    ("deadzone: 2\n", r"deadzone: expected a number in \[0, 1\)"),
    ("buttons: 3\n", "unknown field 'buttons'"),
    ("mode: polar\n", "mode: expected one of joint, cartesian"),
    ("point: fingertip\n", "point: expected the name of a tracked point, with mode: cartesian"),
    ("mode: cartesian\n", "axes: mode: cartesian needs its axes"),
    ("[1, 2\n", "not YAML"),
])
def test_a_bad_mapping_file_is_one_line_naming_the_field(tmp_path, text, error):
    path = tmp_path / "pad.yaml"
    path.write_text(text)
    with pytest.raises(UserError, match=error) as info:
        load_mapping(path)
    assert str(info.value).startswith(str(path)) and "\n" not in str(info.value)


def test_the_playstation_file_has_joy_linux_layout_where_it_differs_from_the_xbox_one():
    xbox, ps = load_mapping(XBOX_YAML), load_mapping(PS_YAML)
    assert (ps.mode, ps.success, ps.failure, ps.deadzone) == (xbox.mode, 0, 1, xbox.deadzone)  # cross / circle
    assert (xbox.deadman, ps.deadman) == (9, 4)  # LB under joy (SDL), L1 under joy_linux (the kernel's order)
    assert ps.axes[0] == xbox.axes[0] == (0, -1.0) and ps.axes[2] == xbox.axes[2] == (1, 1.0)  # the left stick
    assert (xbox.axes[1], ps.axes[1]) == ((2, -1.0), (3, -1.0)) and (xbox.axes[3], ps.axes[3]) == ((3, 1.0), (4, 1.0))
    # a DualShock 4 under joy_linux: 8 axes, 13 buttons; L1 held, right stick right
    pad = GamepadTeleop(ps, act_dim=2)
    axes, buttons = [0.0] * 8, [0] * 13
    axes[3], buttons[4] = -0.5, 1
    _, problem = pad.on_joy(axes, buttons)
    assert problem is None
    np.testing.assert_array_equal(pad.decide(), np.array([0.0, 0.5], np.float32))


def fingertip_after(task_name: str, axes: dict, steps: int = 20, seed: int = 3):
    """Where the fingertip moves in ``steps`` real MuJoCo steps of the shipped Cartesian mapping
    with the dead-man held and the sticks at ``axes``, and the actions taken."""
    from offline_rl_core.task.envs import make_env
    from offline_rl_core.task.spec import load_task

    task = load_task(task_name)
    pad = GamepadTeleop.for_task(load_mapping(CARTESIAN_YAML), task)
    env = make_env(task)
    env.reset(seed)
    pad.on_joy(*joy(axes, pressed={9}))
    start = env.point_positions()["fingertip"].copy()
    actions = []
    for _ in range(steps):
        actions.append(pad.decide(env.joint_positions, env.joint_velocities, env.goal))
        env.step(actions[-1])
    return env.point_positions()["fingertip"] - start, np.array(actions)


@pytest.mark.parametrize("task, axes, direction", [
    ("pusher_reach", {0: -1.0}, [1, 0, 0]),  # left stick right: +x
    ("pusher_reach", {1: -1.0}, [0, -1, 0]),  # left stick down: -y
    ("pusher7_reach", {0: -1.0}, [1, 0, 0]),
    ("pusher7_reach", {3: 1.0}, [0, 0, 1]),  # right stick up: +z
])
def test_cartesian_mode_moves_the_fingertip_in_the_sticks_direction(task, axes, direction):
    moved, actions = fingertip_after(task, axes)
    direction = np.array(direction, np.float64)
    along = moved @ direction
    assert along > 0.005, moved  # metres, in twenty steps (the first few carry the joints' own lag)
    assert np.linalg.norm(moved - along * direction) < 0.5 * along, moved  # mostly that way
    assert actions.dtype == np.float32 and np.all(np.abs(actions) <= 1.0)


def test_cartesian_mode_stays_finite_and_in_range_at_a_singular_pose_and_on_bad_states():
    from offline_rl_core.task.spec import load_task

    pad = GamepadTeleop.for_task(load_mapping(CARTESIAN_YAML), load_task("pusher_reach"))
    pad.on_joy(*joy({0: -1.0}, pressed={9}))  # outward, beyond the arm's reach, from the stretched arm
    action = pad.decide([0.0, 0.0], [0.0, 0.0], [0.1, 0.1])
    assert np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0)
    action = pad.decide([float("nan"), 0.0], [0.0, 0.0], [0.1, 0.1])
    np.testing.assert_array_equal(action, np.zeros(2, np.float32))  # never NaN: no torque
    pad.on_joy(*joy({0: -1.0}))  # released
    assert pad.decide([0.0, 0.0], [0.0, 0.0], [0.1, 0.1]) is None


def test_cartesian_mode_names_a_point_the_task_lacks(tmp_path):
    from offline_rl_core.task.spec import load_task

    path = tmp_path / "pad.yaml"
    path.write_text("mode: cartesian\npoint: elbow\naxes: [{axis: 0, scale: 0.01}]\n")
    with pytest.raises(UserError, match="has no tracked point 'elbow'"):
        GamepadTeleop.for_task(load_mapping(path), load_task("pusher_reach"))
