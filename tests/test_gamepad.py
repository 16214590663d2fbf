"""The gamepad corrector's mapping and rule (no DDS; over ROS through the mux: test_ros_viz)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from offline_rl_core.common.errors import UserError
from offline_rl_core.nodes.gamepad import GamepadMapping, GamepadTeleop, label_json, load_mapping
from ros_helpers import REPO

XBOX_YAML = REPO / "ros_ws" / "src" / "corrections" / "config" / "gamepad_xbox.yaml"


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
    ("[1, 2\n", "not YAML"),
])
def test_a_bad_mapping_file_is_one_line_naming_the_field(tmp_path, text, error):
    path = tmp_path / "pad.yaml"
    path.write_text(text)
    with pytest.raises(UserError, match=error) as info:
        load_mapping(path)
    assert str(info.value).startswith(str(path)) and "\n" not in str(info.value)
