"""The import rule of ARCHITECTURE.md, checked on every import of the package (function-level
ones too): a module imports only from its own folder or from the layers below it, and no
modules import each other in a circle."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "offline_rl_core"

# bottom to top; folders of one rank are peers and do not import each other
LAYERS = [("common",), ("task",), ("data",), ("serving",), ("learners", "evaluation"), ("fast",), ("runs",),
          ("nodes",), ("pipelines",), ("benchmarks",), ("commands",)]
RANK = {folder: rank for rank, folders in enumerate(LAYERS) for folder in folders}
# who may import these at all (beyond what the ranks allow)
ONLY_FROM = {
    "benchmarks": {"offline_rl_core.benchmarks", "offline_rl_core.commands.bench"},
    # the speed layer registers itself when ``runs`` is imported; the bench reports its kernels
    "fast": {"offline_rl_core.fast", "offline_rl_core.runs", "offline_rl_core.benchmarks"},
}
# packages outside the project that only some layers may import
EXTERNAL_ONLY_FROM = {"ros2_shim": ("pipelines",), "rclpy": (), "rosidl_runtime_py": ()}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in a file, at any depth; ``from X import y``
    names X.y where that is a module of the package."""
    tree = ast.parse(path.read_text(), filename=str(path))
    here = module_name(path).split(".")
    package = here if path.name == "__init__.py" else here[:-1]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[: len(package) - node.level + 1] + ([base] if base else []))
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                found.append((node.lineno, sub if _is_module(sub) else base))
    return found


def _is_module(name: str) -> bool:
    path = REPO.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def folder_of(module: str) -> str | None:
    """The layer folder of a project module (None: the package's own __init__/__main__)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in RANK else None


def all_modules() -> dict[str, Path]:
    return {module_name(p): p for p in PACKAGE.rglob("*.py")}


def test_every_folder_of_the_package_is_a_layer():
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert folders == set(RANK), "a new folder needs its place in ARCHITECTURE.md and in LAYERS here"
    loose = sorted(p.name for p in PACKAGE.glob("*.py") if p.name not in ("__init__.py", "__main__.py"))
    assert not loose, f"modules outside any layer: {loose}"


def test_no_module_imports_upward_or_across():
    problems = []
    for name, path in all_modules().items():
        src = folder_of(name)
        for line, target in imports_of(path):
            top = target.split(".")[0]
            if top in EXTERNAL_ONLY_FROM and src not in EXTERNAL_ONLY_FROM[top]:
                problems.append(f"{path.relative_to(REPO)}:{line}: {top} is for {EXTERNAL_ONLY_FROM[top] or 'no layer'}")
            if not target.startswith("offline_rl_core.") or src is None:
                continue
            dst = folder_of(target)
            if dst is None:
                problems.append(f"{path.relative_to(REPO)}:{line}: imports the package facade ({target})")
                continue
            allowed = ONLY_FROM.get(dst)
            if allowed is not None and dst != src and not any(name == a or name.startswith(a + ".") for a in allowed):
                problems.append(f"{path.relative_to(REPO)}:{line}: {dst}/ is imported only by {sorted(allowed)}")
            elif dst != src and RANK[dst] >= RANK[src]:
                problems.append(f"{path.relative_to(REPO)}:{line}: {src}/ imports {target} ({dst}/ is "
                                f"{'beside' if RANK[dst] == RANK[src] else 'above'} it)")
    assert not problems, "imports against the layer rule:\n" + "\n".join(problems)


def test_no_modules_import_each_other_in_a_circle():
    modules = all_modules()
    graph = {name: sorted({t for _, t in imports_of(path) if t in modules and t != name})
             for name, path in modules.items()}
    cycles = strongly_connected(graph)
    assert not cycles, "modules that import each other in a circle:\n" + "\n".join(" -> ".join(c) for c in cycles)


def strongly_connected(graph: dict[str, list[str]]) -> list[list[str]]:
    """Tarjan's algorithm: the components of more than one module."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_the_rule_catches_an_upward_and_a_hidden_import(tmp_path, monkeypatch):
    """The checker itself: a function-level upward import is found."""
    global REPO, PACKAGE
    fake = tmp_path / "offline_rl_core"
    for folder in RANK:
        (fake / folder).mkdir(parents=True)
        (fake / folder / "__init__.py").write_text("")
    (fake / "__init__.py").write_text("")
    (fake / "common" / "a.py").write_text("def f():\n    from ..runs import b\n")
    (fake / "runs" / "b.py").write_text("from ..common import a\n")
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", fake)
    with pytest.raises(AssertionError, match="common/ imports offline_rl_core.runs.b"):
        test_no_module_imports_upward_or_across()
    with pytest.raises(AssertionError, match="offline_rl_core.common.a -> offline_rl_core.runs.b"):
        test_no_modules_import_each_other_in_a_circle()


def test_importing_the_package_loads_no_layer():
    """``import offline_rl_core`` (what every node's first project import runs) loads only
    the package itself: the bag code, torch and gymnasium load when something asks for them."""
    code = ("import sys, offline_rl_core; "
            "print(sorted(m for m in sys.modules if m.startswith('offline_rl_core.') or m in ('torch', 'gymnasium')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_ray_is_imported_by_the_ray_engine_alone_and_lazily():
    """Ray is optional: one module imports it, inside its functions, so the command line, the
    sweep and the local engine load without it."""
    importers = sorted(name for name, path in all_modules().items()
                       if any(t == "ray" or t.startswith("ray.") for _, t in imports_of(path)))
    assert importers == ["offline_rl_core.runs.ray_engine"]
    code = ("import sys; import offline_rl_core.commands.cli as c; c.build_parser(); "
            "import offline_rl_core.runs.ray_engine, offline_rl_core.runs.local_engine, offline_rl_core.data.fleet; "
            "print('ray' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
