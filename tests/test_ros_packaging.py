"""The ROS packages install into a virtualenv (ament prefix) and build with colcon."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest


from ros_helpers import MODULES, PACKAGES, REPO, require_ros
import ros_install  # noqa: E402 - from ros_ws/tools, on the path ros_helpers sets

SRC = REPO / "ros_ws" / "src"


def fake_venv(root: Path) -> Path:
    venv = root / "venv"
    (venv / "bin").mkdir(parents=True)
    (venv / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages").mkdir(parents=True)
    (venv / "bin" / "python").symlink_to(sys.executable)
    return venv


def test_every_package_declares_node_and_real_dependencies():
    for name in PACKAGES:
        package = ros_install.read_package(SRC / name)
        assert package.name == name
        assert package.console_scripts == [("node", f"{MODULES[name]}.node", "main")]
        assert package.modules == [MODULES[name]]
        xml = (SRC / name / "package.xml").read_text()
        assert "<build_type>ament_python</build_type>" in xml and "<exec_depend>rclpy</exec_depend>" in xml
        assert (SRC / name / "resource" / name).exists()
        assert f"install_scripts=$base/lib/{name}" in (SRC / name / "setup.cfg").read_text()


# (package, module with PARAMS, config file): each node's every setting, installed with its package
CONFIGS = [("sim", "pusher_sim.node", "sim"), ("policy", "pusher_policy.node", "policy"),
           ("trainer", "pusher_trainer.node", "trainer"), ("corrections", "pusher_corrections.mux", "mux"),
           ("corrections", "pusher_corrections.corrector", "corrector"), ("learner", "pusher_learner.node", "learner"),
           ("recorder", "pusher_recorder.node", "recorder"), ("viz", "pusher_viz.markers", "markers")]


def test_config_files_hold_every_setting_with_its_default():
    require_ros()
    import importlib

    import yaml

    for package, module, name in CONFIGS:
        params = importlib.import_module(module).PARAMS
        text = (SRC / package / "config" / f"{name}.yaml").read_text()
        values = yaml.safe_load(text)["/**"]["ros__parameters"]
        assert values == {p.name: p.default for p in params if p.default not in (None, [])}, \
            f"{name}: run ros_ws/tools/write_param_configs.py"
        assert all(f"# {p.name}: (unset)" in text for p in params if p.default in (None, [])), name


def test_ros_install_lays_out_an_ament_prefix_and_is_idempotent(tmp_path, capsys):
    venv = fake_venv(tmp_path)
    packages = (*PACKAGES, "corrections", "pusher_common", "viz")
    args = ["--venv", str(venv), "--no-shim", *[str(SRC / p) for p in packages]]
    for _ in range(2):
        assert ros_install.main(args) == 0
    site = ros_install.site_packages(venv)
    for package, _, config in CONFIGS:
        assert (venv / "share" / package / "config" / f"{config}.yaml").is_file()
    for name in PACKAGES:
        assert (venv / "share" / "ament_index" / "resource_index" / "packages" / name).is_file()
        assert (venv / "share" / name / "package.xml").resolve() == (SRC / name / "package.xml").resolve()
        module = MODULES[name]
        assert (site / module).resolve() == (SRC / name / module).resolve()  # symlink: edits are live
        exe = venv / "lib" / name / "node"
        assert os.access(exe, os.X_OK)
        text = exe.read_text()
        assert text.startswith(f"#!{venv.absolute()}/bin/python\n") and f"from {module}.node import main" in text
    # the shared plumbing: a library package, importable, with no executables
    assert (site / "pusher_common").resolve() == (SRC / "pusher_common" / "pusher_common").resolve()
    assert not (venv / "lib" / "pusher_common").exists()
    assert not (venv / "bin" / "node").exists()  # never shadows Node.js
    assert "installed into" in capsys.readouterr().out


def test_ros_install_drops_the_link_of_a_renamed_module(tmp_path):
    venv = fake_venv(tmp_path)
    pkg = tmp_path / "src" / "demo"
    (pkg / "demo").mkdir(parents=True)
    (pkg / "demo" / "__init__.py").write_text("")
    (pkg / "package.xml").write_text("<package format='3'><name>demo</name></package>")
    (pkg / "setup.py").write_text("from setuptools import setup\nsetup()\n")
    assert ros_install.main(["--venv", str(venv), "--no-shim", str(pkg)]) == 0
    site = ros_install.site_packages(venv)
    assert (site / "demo").is_symlink()
    (pkg / "demo").rename(pkg / "pusher_demo")
    assert ros_install.main(["--venv", str(venv), "--no-shim", str(pkg)]) == 0
    assert (site / "pusher_demo").resolve() == (pkg / "pusher_demo").resolve()
    assert not (site / "demo").is_symlink()  # no dangling link to the old module name


def test_ros_install_refuses_a_non_package(tmp_path, capsys):
    venv = fake_venv(tmp_path)
    assert ros_install.main(["--venv", str(venv), "--no-shim", str(tmp_path)]) == 2
    assert "no package.xml" in capsys.readouterr().err


@pytest.mark.slow
def test_colcon_builds_the_workspace(tmp_path):
    colcon = Path(sys.prefix) / "bin" / "colcon"
    if not colcon.exists():
        pytest.skip("colcon is not installed (pip install -e '.[dev]')")
    ws = tmp_path / "ws"
    shutil.copytree(REPO / "ros_ws", ws, ignore=shutil.ignore_patterns("build", "install", "log", "__pycache__"))
    result = subprocess.run(
        [str(colcon), "--log-base", "log", "build", "--base-paths", "src", "tools",
         "--event-handlers", "console_direct-"],
        cwd=ws, capture_output=True, text=True, timeout=240,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    for name in PACKAGES:
        assert (ws / "install" / name / "lib" / name / "node").is_file(), name
        assert (ws / "install" / name / "share" / "ament_index" / "resource_index" / "packages" / name).exists()
    for package, _, config in CONFIGS:
        assert (ws / "install" / package / "share" / package / "config" / f"{config}.yaml").is_file()
    assert not (ws / "install" / "ros2_shim").exists()  # tools/ carries COLCON_IGNORE
    assert (ws / "install" / "pusher_bringup" / "share" / "pusher_bringup" / "launch" / "serve.launch.yaml").is_file()

    # colcon test runs each package's ament template tests (flake8, pep257), and they pass
    tested = subprocess.run([str(colcon), "--log-base", "log", "test", "--base-paths", "src", "tools",
                             "--event-handlers", "console_direct-"], cwd=ws, capture_output=True, text=True, timeout=400)
    assert tested.returncode == 0, tested.stdout[-2000:] + tested.stderr[-2000:]
    result = subprocess.run([str(colcon), "test-result", "--test-result-base", "build", "--verbose"], cwd=ws,
                            capture_output=True, text=True, timeout=60)
    summary = re.search(r"Summary: (\d+) tests, (\d+) errors, (\d+) failures", result.stdout)
    assert summary and int(summary.group(1)) >= 12 and summary.group(2, 3) == ("0", "0"), result.stdout[-2000:]
