"""ROS 2 launch files (YAML format) read into process command lines, without ROS.

The pipelines ship as launch files (``ros_ws/src/pusher_bringup/launch/*.launch.yaml``)
that ``ros2 launch`` runs on a full ROS install. ``make demo``, ``offline-rl hil`` and
this project's ``ros2 launch`` start their nodes from the same files through this
reader, so the files are exercised by the tests and cannot drift. It reads the subset
they use:

    launch:
    - arg: {name: seed, default: "0", description: "..."}
    - node:
        pkg: sim
        exec: node
        name: sim                      # -> -r __node:=sim
        namespace: $(var namespace)    # -> -r __ns:=/...
        args: "--flag value"           # split like a shell line
        if: $(var closed_loop)         # or unless:
        on_exit: shutdown              # the launch ends when this node does
        param:
        - {name: mode, value: lockstep}
        - {from: $(find-pkg-share sim)/config/sim.yaml}
        remap:
        - {from: pusher/command, to: policy/action}

Substitutions: ``$(var NAME)``, ``$(find-pkg-share PKG)``, ``$(env NAME [DEFAULT])``,
``$(equals A B)`` / ``$(not-equals A B)`` (``true`` or ``false``) and ``$(if COND A [B])``,
nested innermost first, as launch does (words split at spaces).
A parameter value given as text is read as YAML after substitution ("5" is an integer),
as launch_ros does. Anything else (include, group, let, other substitutions) is refused
with a message naming the file, rather than ignored.
"""

from __future__ import annotations

import json
import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from ros2_shim import ament_index
from ros2_shim.ament_index import ros2_run
from offline_rl_core.common.errors import UserError

REPO_SRC = Path(__file__).resolve().parents[3] / "src"  # ros_ws/src of this checkout
NODE_KEYS = {"pkg", "exec", "name", "namespace", "args", "param", "remap", "if", "unless", "on_exit", "output"}
# innermost first: a substitution's arguments may be substitutions ($(if $(equals ...) a b))
SUBSTITUTION = re.compile(r"\$\((?P<kind>[a-z-]+)(?P<rest>[^()$]*)\)")


@dataclass
class LaunchNode:
    """One node of a launch file, resolved: what to run and with which ROS arguments."""

    package: str
    executable: str
    name: str | None = None
    namespace: str | None = None
    args: list[str] = field(default_factory=list)
    params: dict = field(default_factory=dict)
    params_files: list[str] = field(default_factory=list)
    remaps: list[tuple[str, str]] = field(default_factory=list)
    shutdown_on_exit: bool = False

    @property
    def label(self) -> str:
        return self.name or self.executable

    def ros_args(self) -> list[str]:
        out: list[str] = []
        if self.name:
            out += ["-r", f"__node:={self.name}"]
        if self.namespace:
            out += ["-r", f"__ns:={self.namespace}"]
        for path in self.params_files:
            out += ["--params-file", path]
        for key, value in self.params.items():
            out += ["-p", f"{key}:={_yaml_value(value)}"]
        for src, dst in self.remaps:
            out += ["-r", f"{src}:={dst}"]
        return out

    def command(self) -> list[str]:
        """The command line, as ``ros2 run`` would exec it."""
        ros_args = self.ros_args()
        return ros2_run(self.package, self.executable, *self.args, *(["--ros-args", *ros_args] if ros_args else []))


def _yaml_value(value) -> str:
    """A ``-p name:=VALUE`` value that rcl's YAML reading gives back unchanged."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    return json.dumps(value)  # strings and lists: JSON is YAML, quoted where needed


def find_launch_file(package: str, file_name: str) -> Path:
    """``share/<package>/launch/<file>`` of the installed package, else the source tree's."""
    candidates = []
    share = ament_index.package_share(package)
    if share is not None:
        candidates.append(share / "launch" / file_name)
    elif not (REPO_SRC / package).is_dir():
        raise UserError(f"Package '{package}' not found")
    candidates.append(REPO_SRC / package / "launch" / file_name)
    for path in candidates:
        if path.is_file():
            return path
    raise UserError(f"launch file {file_name!r} not found in package {package!r} (looked in "
                    f"{', '.join(str(c.parent) for c in candidates)})")


class _Context:
    def __init__(self, path: Path, arguments: dict[str, str]):
        self.path = path
        self.given = dict(arguments)
        self.values: dict[str, str] = {}

    def error(self, what: str) -> UserError:
        return UserError(f"launch file {self.path}: {what}")

    def substitute(self, value) -> str:
        """``value`` with every ``$(...)`` replaced."""
        text = str(value)

        def one(match: re.Match) -> str:
            kind, rest = match.group("kind"), match.group("rest").split()
            if kind == "var" and len(rest) == 1:
                if rest[0] not in self.values:
                    raise self.error(f"$(var {rest[0]}) is not a declared launch argument")
                return self.values[rest[0]]
            if kind == "find-pkg-share" and len(rest) == 1:
                share = ament_index.package_share(rest[0])
                if share is None:
                    raise self.error(f"$(find-pkg-share {rest[0]}): package {rest[0]!r} is not installed")
                return str(share)
            if kind == "env" and len(rest) in (1, 2):
                import os

                if rest[0] in os.environ:
                    return os.environ[rest[0]]
                if len(rest) == 2:
                    return rest[1].strip("'\"")
                raise self.error(f"$(env {rest[0]}): environment variable not set")
            if kind in ("equals", "not-equals") and len(rest) == 2:  # launch's own: 'true' or 'false'
                return str((rest[0] == rest[1]) == (kind == "equals")).lower()
            if kind == "if" and len(rest) in (2, 3):  # $(if CONDITION VALUE [ELSE])
                if rest[0].lower() not in ("true", "false", "1", "0"):
                    raise self.error(f"{match.group(0)}: the condition must be true or false")
                return rest[1] if rest[0].lower() in ("true", "1") else (rest[2] if len(rest) == 3 else "")
            raise self.error(f"substitution {match.group(0)} is not supported here "
                             f"(var, find-pkg-share, env, equals, not-equals, if)")

        while True:
            text, n = SUBSTITUTION.subn(one, text)
            if not n:
                return text

    def condition(self, spec: dict) -> bool:
        for key, wanted in (("if", True), ("unless", False)):
            if key in spec:
                text = self.substitute(spec[key]).strip().lower()
                if text not in ("true", "false", "1", "0"):
                    raise self.error(f"{key}: expected true or false, got {text!r}")
                if (text in ("true", "1")) != wanted:
                    return False
        return True

    def typed(self, value):
        """A parameter value: text is read as YAML after substitution ("5" is 5), as launch_ros does."""
        if isinstance(value, str):
            text = self.substitute(value)
            if not text.strip():
                return ""
            parsed = yaml.safe_load(text)
            return parsed if isinstance(parsed, (bool, int, float, str, list)) else text
        if isinstance(value, list):
            return [self.typed(v) for v in value]
        return value


def load_launch(path: str | Path, arguments: dict[str, str] | None = None) -> list[LaunchNode]:
    """The nodes a launch file starts, in file order, for these launch arguments."""
    path = Path(path)
    try:
        document = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise UserError(f"launch file {path}: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise UserError(f"launch file {path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    ctx = _Context(path, arguments or {})
    if not isinstance(document, dict) or not isinstance(document.get("launch"), list):
        raise ctx.error("expected a top-level 'launch:' list")
    nodes: list[LaunchNode] = []
    for entry in document["launch"]:
        if not isinstance(entry, dict) or len(entry) != 1:
            raise ctx.error(f"each entry must be one action (arg, node), got {entry!r}")
        (kind, spec), = entry.items()
        if kind == "arg":
            _declare_argument(ctx, spec)
        elif kind == "node":
            node = _node(ctx, spec)
            if node is not None:
                nodes.append(node)
        else:
            raise ctx.error(f"action {kind!r} is not supported here (arg, node)")
    return nodes


def declared_arguments(path: str | Path) -> list[dict]:
    """The ``arg`` entries of a launch file (name, default, description) for help texts."""
    document = yaml.safe_load(Path(path).read_text()) or {}
    return [entry["arg"] for entry in document.get("launch", []) if isinstance(entry, dict) and "arg" in entry]


def _declare_argument(ctx: _Context, spec: dict) -> None:
    name = spec.get("name") if isinstance(spec, dict) else None
    if not name:
        raise ctx.error(f"arg needs a name, got {spec!r}")
    if name in ctx.given:
        ctx.values[name] = str(ctx.given[name])
    elif "default" in spec:
        ctx.values[name] = ctx.substitute(spec["default"])
    else:
        raise UserError(f"launch argument {name!r} is required ({ctx.path.name}): pass {name}:=VALUE")


def _node(ctx: _Context, spec: dict) -> LaunchNode | None:
    if not isinstance(spec, dict) or not spec.get("pkg") or not spec.get("exec"):
        raise ctx.error(f"node needs pkg and exec, got {spec!r}")
    unknown = set(spec) - NODE_KEYS
    if unknown:
        raise ctx.error(f"node {spec.get('name', spec['exec'])!r}: {', '.join(sorted(unknown))} not supported here")
    if not ctx.condition(spec):
        return None
    namespace = ctx.substitute(spec.get("namespace", "")).strip()
    if namespace and not namespace.startswith("/"):
        namespace = "/" + namespace
    node = LaunchNode(
        package=ctx.substitute(spec["pkg"]),
        executable=ctx.substitute(spec["exec"]),
        name=ctx.substitute(spec["name"]) if spec.get("name") else None,
        namespace=namespace or None,
        args=shlex.split(ctx.substitute(spec.get("args", ""))),
        shutdown_on_exit=str(spec.get("on_exit", "")).strip() == "shutdown",
    )
    for param in spec.get("param", []) or []:
        if "from" in param:
            node.params_files.append(ctx.substitute(param["from"]))
        elif "name" in param and "value" in param:
            node.params[param["name"]] = ctx.typed(param["value"])
        else:
            raise ctx.error(f"node {node.label!r}: a param needs name and value, or from, got {param!r}")
    for remap in spec.get("remap", []) or []:
        if "from" not in remap or "to" not in remap:
            raise ctx.error(f"node {node.label!r}: a remap needs from and to, got {remap!r}")
        node.remaps.append((ctx.substitute(remap["from"]), ctx.substitute(remap["to"])))
    return node


def parse_launch_arguments(items: list[str]) -> dict[str, str]:
    """``name:=value`` words of a ``ros2 launch`` command line."""
    arguments = {}
    for item in items:
        name, sep, value = item.partition(":=")
        if not sep or not name:
            raise UserError(f"launch argument {item!r}: expected NAME:=VALUE")
        arguments[name] = value
    return arguments
