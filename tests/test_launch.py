"""The launch-file reader (ros2_shim.launch_files) on the shipped pipelines, without ROS."""

from __future__ import annotations

import sys

import pytest

from offline_rl_core.common.errors import UserError
from ros2_shim.launch_files import find_launch_file, load_launch, parse_launch_arguments

from ros_helpers import REPO

LAUNCH_DIR = REPO / "ros_ws" / "src" / "pusher_bringup" / "launch"


def by_label(nodes):
    return {n.label: n for n in nodes}


def test_serve_launch_becomes_ros2_run_command_lines():
    nodes = by_label(load_launch(LAUNCH_DIR / "serve.launch.yaml", {
        "checkpoint": "runs/x/policy.pt", "seed": "7", "episodes": "3", "summary": "/tmp/s.json", "namespace": "arm2"}))
    # a policy that cannot start ends the launch at once, as the sim's last episode does
    assert list(nodes) == ["policy", "sim"] and nodes["sim"].shutdown_on_exit and nodes["policy"].shutdown_on_exit
    sim = nodes["sim"]
    assert sim.params == {"mode": "lockstep", "seed": 7, "episodes": 3, "summary": "/tmp/s.json"}  # typed as YAML
    cmd = sim.command()
    assert cmd[0].endswith("lib/sim/node") or cmd[1:3] == ["run", "sim"]
    ros_args = cmd[cmd.index("--ros-args") + 1:]
    assert ros_args == ["-r", "__node:=sim", "-r", "__ns:=/arm2", "-p", 'mode:="lockstep"', "-p", "seed:=7",
                        "-p", "episodes:=3", "-p", 'summary:="/tmp/s.json"', "-r", "pusher/command:=policy/action"]
    # the policy runs in the sim's mode: its watchdog only where the sim runs in realtime
    assert nodes["policy"].params == {"checkpoint": "runs/x/policy.pt", "task": "", "poll_period": 0.5,
                                      "mode": "lockstep", "publish_command": True}
    served_only = load_launch(LAUNCH_DIR / "serve.launch.yaml", {"checkpoint": "c.pt", "closed_loop": "false",
                                                                 "publish_command": "false"})
    assert [n.label for n in served_only] == ["policy"]  # if: $(var closed_loop)
    # served for a mux (the corrections rounds): the policy answers on policy/action only
    assert served_only[0].params["publish_command"] is False


def test_the_task_argument_reaches_the_nodes_that_read_the_task():
    """``task:=`` (a built-in task or a task file) goes to every node of ours that reads it."""
    online = by_label(load_launch(LAUNCH_DIR / "online.launch.yaml", {"task": "/tmp/arm.yaml"}))
    assert {n: online[n].params["task"] for n in ("learner", "policy", "mux", "corrector")} == \
        dict.fromkeys(("learner", "policy", "mux", "corrector"), "/tmp/arm.yaml")
    assert by_label(load_launch(LAUNCH_DIR / "online.launch.yaml", {}))["mux"].params["task"] == "pusher_reach"
    corrections = by_label(load_launch(LAUNCH_DIR / "corrections.launch.yaml", {"out": "b.db3", "task": "arm"}))
    assert {n: corrections[n].params["task"] for n in ("policy", "mux", "corrector", "sim")} == \
        dict.fromkeys(("policy", "mux", "corrector", "sim"), "arm")
    served = by_label(load_launch(LAUNCH_DIR / "serve.launch.yaml", {"checkpoint": "c.pt", "task": "arm"}))
    assert served["policy"].params["task"] == "arm"


def test_every_shipped_launch_file_reads_with_its_required_arguments():
    required = {"record.launch.yaml": {"out": "b.db3"}, "serve.launch.yaml": {"checkpoint": "c.pt"},
                "corrections.launch.yaml": {"out": "b.db3", "checkpoint": "c.pt"}, "online.launch.yaml": {}}
    assert sorted(p.name for p in LAUNCH_DIR.glob("*.launch.yaml")) == sorted(required)
    for name, arguments in required.items():
        nodes = load_launch(find_launch_file("pusher_bringup", name), arguments)
        # one node ends each pipeline, and the policy node when it cannot start
        assert sum(n.shutdown_on_exit and n.label != "policy" for n in nodes) == 1, name
        if arguments:
            with pytest.raises(UserError, match=f"launch argument '{next(iter(arguments))}' is required"):
                load_launch(LAUNCH_DIR / name, {})
    corrections = load_launch(LAUNCH_DIR / "corrections.launch.yaml", {"out": "b.db3", "with_policy": "false"})
    assert [n.label for n in corrections] == ["mux", "corrector", "recorder", "sim"]  # the start order hil relies on
    online = by_label(load_launch(LAUNCH_DIR / "online.launch.yaml", {"corrector": "none"}))
    assert list(online) == ["learner", "policy", "mux", "recorder", "sim"]  # the learner serves first
    assert online["policy"].params["weights_topic"] == "learner/weights"
    # the session's key pair: the learner signs with the private key, the policy node checks the public one
    assert online["learner"].params["signing_key"] == "runs/hil-online/keys/weights.key"
    assert online["policy"].params["weights_key"] == "runs/hil-online/keys/weights.pub"
    assert online["mux"].params["require_teleop"] is False  # no corrector: the mux waits for no teleop
    assert online["policy"].params["paced_every"] == 50  # lockstep: paced by publish_every
    # a new out directory is made by the nodes that write into it
    assert "--make-parents" in online["recorder"].args
    online = by_label(load_launch(LAUNCH_DIR / "online.launch.yaml", {"mode": "realtime"}))
    assert online["policy"].params["paced_every"] == 0 and online["mux"].params["require_teleop"] is True
    assert "corrector" in online
    recorder = by_label(corrections)["recorder"]
    assert recorder.args == ["--passive", "--episodes", "30", "--out", "b.db3", "--overwrite"]


def test_unsupported_launch_content_is_refused_naming_the_file(tmp_path):
    bad = tmp_path / "bad.launch.yaml"
    bad.write_text("launch:\n- include:\n    file: other.launch.yaml\n")
    with pytest.raises(UserError, match=r"bad.launch.yaml: action 'include' is not supported"):
        load_launch(bad)
    bad.write_text("launch:\n- node:\n    pkg: sim\n    exec: node\n    param:\n    - name: x\n      value: $(eval 1)\n")
    with pytest.raises(UserError, match=r"substitution \$\(eval 1\) is not supported"):
        load_launch(bad)
    bad.write_text("launch:\n- node:\n    pkg: sim\n    exec: node\n    respawn: true\n")
    with pytest.raises(UserError, match="respawn not supported"):
        load_launch(bad)
    with pytest.raises(UserError, match="expected NAME:=VALUE"):
        parse_launch_arguments(["seed=3"])
    with pytest.raises(UserError, match="not found in package 'pusher_bringup'"):
        find_launch_file("pusher_bringup", "none.launch.yaml")


def test_launched_processes_end_with_the_on_exit_node_and_stop_the_rest(tmp_path):
    from ros2_shim.launch_files import LaunchNode

    from offline_rl_core.pipelines.processes import LaunchedProcesses

    server = LaunchNode("x", "server", name="server")
    worker = LaunchNode("x", "worker", name="worker", shutdown_on_exit=True)
    launched = LaunchedProcesses([server, worker], {}, tmp_path)
    launched["server"].cmd = [sys.executable, "-c", "import time; print('up', flush=True); time.sleep(60)"]
    launched["worker"].cmd = [sys.executable, "-c", "print('done')"]
    with launched.start(ready={"server": "up"}):
        assert launched.wait(timeout=30) == 0
        assert launched["server"].running()  # ended by the worker, stopped on leaving the block
    assert not launched["server"].running() and "done" in (tmp_path / "worker.log").read_text()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's")
def test_a_node_does_not_outlive_a_pipeline_that_was_killed(tmp_path):
    """A pipeline SIGKILLed (a timeout, the OOM killer) cannot stop its nodes: they get
    SIGTERM from the kernel instead of driving the arm, and loading the machine, alone."""
    import os
    import signal
    import subprocess
    import time

    parent = subprocess.Popen([sys.executable, "-c", f"""
import sys, time
from offline_rl_core.pipelines.processes import RosProcess
node = RosProcess([sys.executable, "-c", "import time; time.sleep(120)"], {{}}, {str(tmp_path / "node.log")!r}).start()
print(node.pid, flush=True)
time.sleep(120)
"""], stdout=subprocess.PIPE, text=True, cwd=REPO)
    try:
        child = int(parent.stdout.readline())
        assert os.path.exists(f"/proc/{child}")
        parent.kill()
        parent.wait(timeout=10)
        deadline = time.monotonic() + 30
        while os.path.exists(f"/proc/{child}") and time.monotonic() < deadline:
            time.sleep(0.05)  # the kernel's signal, then the exit; reaped by init
        gone = not os.path.exists(f"/proc/{child}") or " Z " in open(f"/proc/{child}/stat").read()
    finally:
        parent.kill()
    if not gone:
        os.kill(child, signal.SIGKILL)
    assert gone, "the node outlived its pipeline"


def test_online_launch_splits_into_one_learner_and_namespaced_actors():
    """Several actors, one learner (hil --online --actors N): the learner alone, subscribed to
    every actor's transitions; each actor without a learner, on the learner's weights."""
    learner = by_label(load_launch(LAUNCH_DIR / "online.launch.yaml", {
        "with_actor": "false", "with_corrector": "false", "actors": "/arm1, /arm2"}))
    assert list(learner) == ["learner"] and learner["learner"].params["actors"] == ["/arm1", "/arm2"]
    actor = load_launch(LAUNCH_DIR / "online.launch.yaml", {
        "with_learner": "false", "namespace": "/arm2", "weights_topic": "/learner/weights"})
    assert [n.label for n in actor] == ["policy", "mux", "corrector", "recorder", "sim"]
    assert {n.namespace for n in actor} == {"/arm2"}
    assert by_label(actor)["policy"].params["weights_topic"] == "/learner/weights"
    assert by_label(load_launch(LAUNCH_DIR / "online.launch.yaml", {}))["learner"].params["actors"] == []


def test_the_online_launch_hands_the_corrector_and_learner_settings_to_their_nodes():
    """What `offline-rl hil --online` passes as launch arguments reaches the node that uses it,
    typed: the corrector's steering and shaky hand, the learner's batch mix and anchor, whether the
    policy node explores, whether the corrector labels the states it leaves to the policy and the
    learner imitates the labels (a person at the keyboard labels none)."""
    nodes = by_label(load_launch(LAUNCH_DIR / "online.launch.yaml", {
        "steer": "stick", "corrector_noise": "0.2", "offline_ratio": "0.25", "bc_weight": "100.0",
        "lr_decay_steps": "20000", "explore": "false", "action_labels": "true", "from_topics": "true"}))
    assert nodes["corrector"].params["action_labels"] is True and nodes["learner"].params["action_labels"] is True
    keyboard = by_label(load_launch(LAUNCH_DIR / "online.launch.yaml", {"action_labels": "true",
                                                                        "corrector": "keyboard"}))
    assert keyboard["corrector"].params["action_labels"] is False
    assert nodes["corrector"].params["steer"] == "stick" and nodes["corrector"].params["noise"] == 0.2
    assert nodes["policy"].params["explore"] is False
    learner = nodes["learner"].params
    assert (learner["offline_ratio"], learner["bc_weight"], learner["lr_decay_steps"]) == (0.25, 100.0, 20000)
    defaults = by_label(load_launch(LAUNCH_DIR / "online.launch.yaml", {}))
    assert defaults["corrector"].params["steer"] == "expert" and defaults["corrector"].params["noise"] == 0.0
    assert defaults["learner"].params["offline_ratio"] == 0.5
    assert defaults["policy"].params["explore"] is True  # the stage samples the learner's Gaussian
    assert not defaults["corrector"].params["action_labels"] and not defaults["learner"].params["action_labels"]
