"""The arm's markers from its joint positions (no DDS; the ROS test is test_ros_viz)."""

from __future__ import annotations

import numpy as np
import pytest

from offline_rl_core.nodes.arm_markers import LINE_LIST, SPHERE, ArmMarkers
from offline_rl_core.task.envs import task_model
from offline_rl_core.task.kinematics import PointKinematics
from offline_rl_core.task.spec import load_task


def by_ns(markers):
    return {m.ns: m for m in markers}


def test_pusher_reach_links_from_mujoco_match_the_planar_chain():
    task = load_task("pusher_reach")
    with_model, planar = ArmMarkers(task, task_model(task)), ArmMarkers(task)
    rng = np.random.default_rng(0)
    for q in [np.zeros(2), *rng.uniform(-np.pi, np.pi, (5, 2))]:
        a, b = by_ns(with_model.markers(q, goal=np.array([0.1, 0.05]))), by_ns(planar.markers(q))
        np.testing.assert_allclose(a["links"].points, b["links"].points, atol=1e-9)
        # the drawn arm ends at the fingertip the task's kinematics computes
        tip = PointKinematics(task).point(task.point("fingertip"), q)
        np.testing.assert_allclose(a["links"].points[-1][:2], tip, atol=1e-9)
        np.testing.assert_allclose(a["points/fingertip"].position[:2], tip, atol=1e-9)
    assert a["links"].type == LINE_LIST and len(a["links"].points) == 4  # two links, in pairs
    assert a["goal"].type == SPHERE and a["goal"].position == (0.1, 0.05, 0.0)
    assert "goal" not in b  # no goal heard yet: none drawn


def test_straight_arm_reaches_along_x():
    markers = by_ns(ArmMarkers(load_task("pusher_reach")).markers([0.0, 0.0]))
    np.testing.assert_allclose(markers["links"].points, [(0, 0, 0), (0.1, 0, 0), (0.1, 0, 0), (0.2, 0, 0)])


def test_the_sims_own_points_are_drawn_where_it_says():
    task = load_task("pusher_reach")
    markers = by_ns(ArmMarkers(task).markers([0.0, 0.0], points={"fingertip": (0.3, 0.2, 0.0)}))
    assert markers["points/fingertip"].position == (0.3, 0.2, 0.0)


def test_seven_joint_arm_in_3d_ends_at_its_fingertip_site():
    pytest.importorskip("gymnasium")
    task = load_task("pusher7_reach")
    model = task_model(task)
    arm = ArmMarkers(task, model)
    q = np.random.default_rng(1).uniform(-0.5, 0.5, len(task.state.joints))
    markers = by_ns(arm.markers(q, goal=np.array([0.5, -0.2, 0.1])))
    links = np.array(markers["links"].points)
    assert len(links) % 2 == 0 and len(links) >= 2 * 7
    tip = PointKinematics(task, model).point(task.point("fingertip"), q)
    assert np.min(np.linalg.norm(links - tip, axis=1)) < 1e-9  # a link ends at the tracked point
    np.testing.assert_allclose(markers["points/fingertip"].position, tip, atol=1e-9)
    assert markers["goal"].position == (0.5, -0.2, 0.1)
    # the joints move the links: another pose, other segments
    other = np.array(by_ns(arm.markers(q + 0.3))["links"].points)
    assert np.max(np.abs(other - links)) > 0.01


def test_foxglove_layout_shows_the_markers_and_plots_the_transition_fields_it_names():
    import json
    import re

    from offline_rl_core.data.transitions import Layout
    from ros_helpers import REPO

    layout = json.loads((REPO / "ros_ws" / "src" / "viz" / "config" / "foxglove_layout.json").read_text())
    panels = layout["configById"]
    assert {p.split("!")[0] for p in panels} == {"3D", "Plot", "DiagnosticSummary", "DiagnosticStatusPanel"}
    assert panels["3D!arm"]["topics"]["/markers"]["visible"] and panels["3D!arm"]["followTf"] == "world"
    assert panels["DiagnosticSummary!nodes"]["topicToRender"] == "/diagnostics"
    task = load_task("pusher_reach")
    slices = Layout(task.obs_dim, task.act_dim).slices
    for panel in ("Plot!success", "Plot!intervention"):
        for path in panels[panel]["paths"]:
            index = re.fullmatch(r"/pusher/transition\.data\[(\d+)\]", path["value"])
            if index:  # the transition row's field the label names
                assert slices[path["label"]].start == int(index.group(1)), path
    # every panel of the layout tree is configured
    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])
    assert sorted(leaves(layout["layout"])) == sorted(panels)
