"""What a learner's training step can change, found by walking its attributes.

A learner keeps its state in plain attributes: modules, loose parameters (SAC's
log-std), optimisers, random generators, and helpers holding more of them (the twin
critic's optimiser). Resume points (``resume.py``) and the undo of a recording that
stopped part-way (``fast.traced.Snapshot``) both need all of it, so both find it here, the
same way; a new learner's state is found without either being told.
"""

from __future__ import annotations

from typing import Iterator

import torch

# Entered for their attributes; these hold their own state (parameters, optimiser state).
_LEAVES = (torch.nn.Module, torch.Tensor, torch.optim.Optimizer, torch.Generator)


def walk(obj, depth: int = 1, prefix: str = "") -> Iterator[tuple[str, object]]:
    """(dotted name, value) of ``obj``'s attributes, the items of its lists and tuples
    (``name.0``, ``name.1``), and, ``depth`` levels down, the same of its helpers."""
    if obj is None or depth < 0 or not hasattr(obj, "__dict__"):
        return
    for name, value in vars(obj).items():
        yield from _values(f"{prefix}{name}", value, depth)


def _values(name: str, value, depth: int) -> Iterator[tuple[str, object]]:
    if isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            if isinstance(item, _LEAVES):
                yield f"{name}.{i}", item
        return
    yield name, value
    if not isinstance(value, _LEAVES):
        yield from walk(value, depth - 1, f"{name}.")


def named(obj, kind, depth: int = 1) -> dict[str, object]:
    """``obj``'s state of type ``kind`` by dotted name (each object once)."""
    found, seen = {}, set()
    for name, value in walk(obj, depth):
        if isinstance(value, kind) and id(value) not in seen:
            seen.add(id(value))
            found[name] = value
    return found


def optimizers_of(obj) -> list[torch.optim.Optimizer]:
    """The optimisers held by a learner (its attributes and theirs)."""
    return list(named(obj, torch.optim.Optimizer, depth=2).values())
