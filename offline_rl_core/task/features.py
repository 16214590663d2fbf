"""A task's observation, reward, success and episode end, for N rows at once (numpy).

What a task file's ``observation`` and ``reward`` sections say, computed from the joint
positions and velocities (in ``robot.state.joints`` order) and the named vectors (``goal``
and the tracked points) of N states. Everything is computed in float64 and the
observation rounded to float32 once, with the same operations the chapter's env uses, so
on ``pusher_reach`` these give its observations and rewards bit for bit
(tests/test_task_spec.py).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .spec import JOINT_STATE, JOINTS_VECTOR, TaskSpec


def wrap_angle(angle):
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def joint_columns(spec: TaskSpec, positions: np.ndarray, names) -> np.ndarray:
    """The named joints' positions (N, k), float64, revolute ones wrapped to [-pi, pi)."""
    index = {j: i for i, j in enumerate(spec.state.joints)}
    cols = np.asarray(positions, dtype=np.float64)[:, [index[j] for j in names]]
    wrap = [k for k, j in enumerate(names) if j in spec.state.revolute]
    if wrap:
        cols[:, wrap] = wrap_angle(cols[:, wrap])
    return cols


def vector(spec: TaskSpec, name: str, positions: np.ndarray, vectors: dict[str, np.ndarray],
           partner: str | None = None) -> np.ndarray:
    """A named vector of N rows, float64: ``joints`` (the state's positions), or one of ``vectors``.
    Compared with a joint-space goal (``partner`` is ``goal``), ``joints`` is in the goal's
    joint order, so that each goal value meets its own joint."""
    if name == JOINTS_VECTOR:
        order = spec.goal.joints if partner == "goal" and spec.goal.type == JOINT_STATE else spec.state.joints
        return joint_columns(spec, positions, order)
    return np.asarray(vectors[name], dtype=np.float64)


def pair(spec: TaskSpec, a: str, b: str, positions, vectors) -> tuple[np.ndarray, np.ndarray]:
    """Vectors ``a`` and ``b``, each value of one facing its own of the other."""
    return vector(spec, a, positions, vectors, partner=b), vector(spec, b, positions, vectors, partner=a)


def observe(spec: TaskSpec, positions, velocities, vectors: dict[str, np.ndarray]) -> np.ndarray:
    """(N, obs_dim) float32 observations of N states.

    ``positions``, ``velocities``: (N, J) in ``spec.state.joints`` order; ``vectors``: the
    goal and each tracked point as (N, size) in their axes (or joints) order.
    """
    positions = np.asarray(positions, dtype=np.float64)
    velocities = np.asarray(velocities, dtype=np.float64)
    n = positions.shape[0]
    index = {j: i for i, j in enumerate(spec.state.joints)}
    parts = []
    for f in spec.observation:
        if f.kind == "cos_sin":
            angles = joint_columns(spec, positions, f.args)
            cos_sin = np.empty((n, 2 * len(f.args)))
            cos_sin[:, 0::2] = np.cos(angles)
            cos_sin[:, 1::2] = np.sin(angles)
            parts.append(cos_sin)
        elif f.kind == "positions":
            parts.append(joint_columns(spec, positions, f.args))
        elif f.kind == "velocities":
            parts.append(velocities[:, [index[j] for j in f.args]])
        elif f.kind == "vector":
            parts.append(vector(spec, f.args[0], positions, vectors))
        elif f.kind == "along_across":
            parts.append(along_across(*(vector(spec, v, positions, vectors) for v in f.args)))
        else:
            va, vb = pair(spec, *f.args, positions, vectors)
            delta = va - vb
            if f.kind == "direction":
                # a unit vector: as telling a centimetre from the goal as a metre, where the
                # difference shrinks toward the resolution an MLP gives its inputs
                length = distances(va, vb)[:, None]
                delta = np.divide(delta, length, out=np.zeros_like(delta), where=length > 0)
            parts.append(delta)
    return np.concatenate(parts, axis=1).astype(np.float32)


def along_across(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(N, 2): ``a - b`` along the unit vector from ``b`` to ``c`` and across it (its left
    normal), zero where ``b`` and ``c`` meet. A pusher's fingertip seen from the puck on the
    line to the goal: behind it, or off it to one side, whichever way the line runs, which a
    network reading the two differences must otherwise learn as a product of them."""
    line = c - b
    length = distances(c, b)[:, None]
    u = np.divide(line, length, out=np.zeros_like(line), where=length > 0)
    d = a - b
    return np.stack([d[:, 0] * u[:, 0] + d[:, 1] * u[:, 1], d[:, 1] * u[:, 0] - d[:, 0] * u[:, 1]], axis=1)


def feature_widths(spec: TaskSpec) -> list[int]:
    """How many observation values each feature of ``spec.observation`` gives, in order."""
    widths = []
    for f in spec.observation:
        if f.kind == "cos_sin":
            widths.append(2 * len(f.args))
        elif f.kind in ("positions", "velocities"):
            widths.append(len(f.args))
        elif f.kind == "vector":
            widths.append(spec.vector_size(f.args[0]))
        elif f.kind == "along_across":
            widths.append(2)
        else:
            widths.append(spec.vector_size(f.args[0], f.args[1]))
    return widths


def success_columns(spec: TaskSpec) -> slice | None:
    """The observation's columns that hold the success distance's difference (``reward.distance``,
    either way round), or None where the observation has no such feature."""
    start = 0
    for f, width in zip(spec.observation, feature_widths(spec)):
        if f.kind == "difference" and set(f.args) == set(spec.reward.distance):
            return slice(start, start + width)
        start += width
    return None


def distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| for N rows, float64 (N,). Elementwise rather than ``np.linalg.norm``: a norm
    goes through BLAS, whose kernel (fused multiply-add or not) depends on the machine."""
    delta = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    total = delta[:, 0] * delta[:, 0]
    for k in range(1, delta.shape[1]):
        total = total + delta[:, k] * delta[:, k]
    return np.sqrt(total)


class StepScore(NamedTuple):
    """The outcome of one control step for N envs, as arrays of length N."""

    reward: np.ndarray  # float64: -distance (and the further terms), plus the success bonus
    dist: np.ndarray  # float64: the reward's (success) distance
    success: np.ndarray  # bool: success after this step (latched, or this state's: reward.success_at)
    terminated: np.ndarray  # bool: success latched and terminate_on_success
    truncated: np.ndarray  # bool: the step count reached max_steps


def score(spec: TaskSpec, positions, vectors: dict[str, np.ndarray], steps, success_before,
          terminate_on_success: bool | None = None, success_now=None) -> StepScore:
    """Reward, success and episode end for N states reached by their ``steps``-th step;
    ``success_before``: each one's success before this step.

    ``success_now`` (bool (N,)): whether each state is a success, as something other than the
    success distance judges it (a person's label, a learned classifier); default: the
    distance under ``success_within``. ``reward.success_at`` latch: success latches the first
    time, with the bonus on that step; end: success is this state's, with the bonus on every
    successful state."""
    dist = distances(*pair(spec, *spec.reward.distance, positions, vectors))
    success_before = np.asarray(success_before, dtype=bool)
    within = dist < spec.reward.success_within if success_now is None else np.asarray(success_now, dtype=bool)
    reward = -dist
    for term in spec.reward.terms:
        reward = reward - term.weight * distances(*pair(spec, *term.distance, positions, vectors))
    if spec.reward.success_at == "end":
        success = within
        reward[success] += spec.reward.success_bonus
    else:
        newly = ~success_before & within
        reward[newly] += spec.reward.success_bonus  # a masked add: -dist + 0.0 would turn -0.0 into +0.0
        success = success_before | newly
    terminate = spec.reward.terminate_on_success if terminate_on_success is None else terminate_on_success
    terminated = success & bool(terminate)
    truncated = np.asarray(steps) >= spec.episodes.max_steps
    return StepScore(reward, dist, success, terminated, truncated)
