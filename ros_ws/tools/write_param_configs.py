"""Write each node's config/<node>.yaml from its PARAMS list (run after changing a node's settings).

    .venv/bin/python ros_ws/tools/write_param_configs.py

tests/test_ros_packaging.py checks that the files hold every setting with its default.
"""
import importlib
from pathlib import Path

import yaml

spec = {
 "sim": [("pusher_sim.node", "sim", "ros2 run sim node")],
 "policy": [("pusher_policy.node", "policy", "ros2 run policy node")],
 "trainer": [("pusher_trainer.node", "trainer", "ros2 run trainer node")],
 "learner": [("pusher_learner.node", "learner", "ros2 run learner node")],
 "recorder": [("pusher_recorder.node", "recorder", "ros2 run recorder node")],
 "corrections": [("pusher_corrections.mux", "mux", "ros2 run corrections mux"),
                 ("pusher_corrections.corrector", "corrector", "ros2 run corrections corrector")],
 "viz": [("pusher_viz.markers", "markers", "ros2 run viz markers"),
         ("pusher_viz.live_view", "live_view", "ros2 run viz live_view")],
}
for pkg, nodes in spec.items():
    d = Path(__file__).resolve().parents[1] / "src" / pkg / "config"
    d.mkdir(exist_ok=True)
    for module, name, cmd in nodes:
        params = importlib.import_module(module).PARAMS
        lines = [f"# Defaults of `{cmd}`: every setting, with its description.",
                 f"# Use: {cmd} --ros-args --params-file $(ros2 pkg prefix {pkg})/share/{pkg}/config/{name}.yaml",
                 "# `/**` matches the node whatever its name or namespace.",
                 "/**:", "  ros__parameters:"]
        for p in params:
            lines.append(f"    # {p.description}" + (" (read-only)" if p.read_only else ""))
            if p.default is None or p.default == []:
                lines.append(f"    # {p.name}: (unset)")
            else:
                v = yaml.safe_dump(p.default, default_flow_style=True).replace("\n...", "").strip()
                lines.append(f"    {p.name}: {v}")
        (d / f"{name}.yaml").write_text("\n".join(lines) + "\n")
