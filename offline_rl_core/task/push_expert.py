"""The scripted pusher of ``pusher_push``: get behind the puck on its line to the goal, then push.

It acts on what a robot and a tracker publish (the joint state, the goal, the puck's x, y),
and its action is a function of those alone, so collection, ``eval --expert`` and the
corrector all call the same function, and a puck that drifts off its line is simply planned
for again at the next state ("replan"):

- **the push line**: ``u``, the unit vector from the puck to the goal. A push starts
  ``standoff`` behind the puck's far side (``contact`` = puck radius + fingertip radius from
  its centre), with the elbow on a side where the links clear the puck all along the push
  (``PushGeometry.push_is_clear``, the reset sampler's own test);
- **getting there**, as the task's ``sim.push.approach`` says:
  ``wave`` (``JointSpacePlanner``, the default): the shortest way through the arm's joint space
  (a grid of ``grid`` x ``grid`` poses on the torus of the two angles) that keeps the links
  ``margin`` from the puck, found by a breadth-first wave from the push's start; the arm
  heads ``lookahead`` cells down the wave, then to the start itself. The wave depends only on
  the puck and the goal: it is computed once for them and reused while they stay put.
  ``orbit``: the fingertip circles the puck at ``orbit`` beyond contact, in the push line's
  frame, the shorter way round to behind it whose arc keeps the links ``margin`` clear with
  the elbow on the side it is (``orbit_arc`` further round each step, spiralling in from
  further out), and goes straight to the push's start once within ``orbit_arc`` of it; where
  no arc is clear on the elbow's side (the push needs the other), the wave. Its torques are a
  simpler function of what the policy observes (the fingertip seen from the puck along its
  line to the goal) than the wave's, so a network imitates it better (``bench/push_bound.py``);
- **pushing**, once the fingertip is behind the puck and within ``align`` of the line: the
  fingertip heads ``depth`` into the puck along ``u`` (``push_gain`` times the distance left,
  at most ``push_depth``, so the puck slows to a stop on the goal, where its dry friction
  holds it; less the further the fingertip is off the line) and ``steer`` times its offset
  past the line (a pushed disc runs away from the fingertip, so an offset grows unless the
  fingertip outruns it), at most ``step`` ahead of where it is, by inverse kinematics with
  the elbow kept on its side;
- **holding**: the puck within ``hold`` (of ``success_within``) of the goal, the arm stands
  still (damping only);
- joint targets become torques by the chapter's law, ``kp (q* - q) - kd q̇``, clipped to the
  motors' [-1, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from .pusher_push import PushGeometry, PushSettings
from .spec import TaskSpec

TWO_PI = 2.0 * math.pi
NEIGHBOURS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
UNREACHED = np.iinfo(np.int32).max
REACH_OUT = 8  # cells searched around a pose too near the puck for one clear of it


@dataclass(frozen=True)
class PushGains:
    kp: float = 25.0  # action per rad (as the chapter's expert)
    kd: float = 1.5  # action per rad/s
    grid: int = 72  # joint-space cells per joint (5 degrees)
    margin: float = 0.004  # m: the links' clearance from the puck on the way (beyond contact)
    lookahead: int = 3  # cells down the wave the arm heads for
    step: float = 0.04  # m: pushing, the fingertip's next point at most this far ahead
    align: float = 0.015  # m: pushing only within this of the push line
    push_gain: float = 1.0  # depth of the push per m of puck-goal distance
    push_depth: float = 0.015  # m: at most this deep into the puck
    steer: float = 1.0  # pushing off the line by x, aim this times x past it on the other side
    nudge: float = 0.02  # m: the puck this near the goal, push it the way it faces (no going round)
    hold: float = 0.3  # of success_within: the puck this close to the goal, the arm stands still
    orbit: float = 0.012  # m beyond contact: the orbit's radius round the puck (approach: orbit)
    orbit_arc: float = math.radians(25)  # rad: the fingertip's next point this far round the orbit
    orbit_spiral: float = 0.03  # m: from further out, this much nearer the orbit each step
    orbit_checks: int = 12  # points along an arc where the links' clearance is checked


def wrap(angle):
    return (np.asarray(angle) + math.pi) % TWO_PI - math.pi


class JointSpacePlanner:
    """Breadth-first waves over the arm's joint-space grid around a puck."""

    def __init__(self, geometry: PushGeometry, cells: int, margin: float):
        self.geometry, self.cells, self.margin = geometry, cells, margin
        self.width = TWO_PI / cells
        self.angles = -math.pi + self.width * np.arange(cells)
        self.elbow, self.tip = geometry.elbow_and_tip(*np.meshgrid(self.angles, self.angles, indexing="ij"))

    def cell(self, q) -> tuple[int, int]:
        i, j = (int(round((float(wrap(a)) + math.pi) / self.width)) % self.cells for a in q)
        return i, j

    def wave(self, puck: np.ndarray, starts: list[tuple[float, float]]) -> np.ndarray:
        """Cells' steps to the nearest of ``starts`` (joint angles) through poses clear of the
        puck; ``UNREACHED`` where blocked or cut off."""
        upper, fore = self.geometry.clearance_of(self.elbow, self.tip, puck)
        open_ = (upper >= self.margin) & (fore >= self.margin)
        dist = np.full((self.cells, self.cells), UNREACHED, np.int32)
        front = np.zeros_like(open_)
        for q in starts:
            front[self.cell(q)] = True  # a start's own cell, whatever the grid's rounding says
        dist[front] = 0
        open_ &= ~front
        steps = 0
        ring = np.zeros((self.cells + 2, self.cells + 2), bool)
        while front.any():
            steps += 1
            ring[1:-1, 1:-1] = front  # on a torus: each edge's neighbours are across it
            ring[0, 1:-1], ring[-1, 1:-1] = front[-1], front[0]
            ring[:, 0], ring[:, -1] = ring[:, -2], ring[:, 1]
            grown = ring[:-2, :-2] | ring[:-2, 1:-1] | ring[:-2, 2:] | ring[1:-1, :-2] | ring[1:-1, 2:] \
                | ring[2:, :-2] | ring[2:, 1:-1] | ring[2:, 2:]
            front = grown & open_
            open_ &= ~front
            dist[front] = steps
        return dist

    def toward(self, q: np.ndarray, dist: np.ndarray, lookahead: int) -> tuple[float, float] | None:
        """Joint angles ``lookahead`` cells down the wave from ``q`` (None: at a start, or no
        way from here)."""
        i, j = self.cell(q)
        n = self.cells
        if dist[i, j] == UNREACHED:  # too near the puck: head for the nearest pose clear of it
            for r in range(1, REACH_OUT + 1):
                ring = [((i + di) % n, (j + dj) % n) for di in range(-r, r + 1) for dj in range(-r, r + 1)
                        if max(abs(di), abs(dj)) == r and dist[(i + di) % n, (j + dj) % n] != UNREACHED]
                if ring:
                    c = min(ring, key=lambda c: dist[c])
                    return float(self.angles[c[0]]), float(self.angles[c[1]])
            return None
        for _ in range(lookahead):
            if dist[i, j] == 0:
                break
            i, j = min((((i + di) % n, (j + dj) % n) for di, dj in NEIGHBOURS), key=lambda c: dist[c])
        if dist[i, j] == 0:
            return None
        return float(self.angles[i]), float(self.angles[j])


class PushExpert:
    """``expert(positions, velocities, goal, points) -> action`` (float32 (2,), in [-1, 1]);
    ``points[settings.point]``: the puck's x, y."""

    def __init__(self, task: TaskSpec, model: mujoco.MjModel, gains: PushGains | None = None):
        self.task = task
        self.settings = PushSettings.of(task)
        self.geometry = PushGeometry.of(task, model, self.settings)
        self.point = self.settings.point
        self.gains = gains or PushGains()
        self.hold = self.gains.hold * task.reward.success_within
        self.planner = JointSpacePlanner(self.geometry, self.gains.grid, self.gains.margin)
        self._plan_for = None  # the puck and goal the plan below is for
        self._plan = None

    def plan(self, puck: np.ndarray, goal: np.ndarray, u: np.ndarray) -> tuple[list, list, np.ndarray]:
        """(the elbow signs a push can start with, the poses it starts from, the wave to them):
        one start per elbow side that clears the puck (both if none does). A function of the
        puck and the goal only: kept for the next state while they stay where they are."""
        key = (*puck, *goal)
        if key != self._plan_for:
            g = self.geometry
            signs = g.push_is_clear(puck, goal, self.settings.standoff, self.gains.margin) or [1.0, -1.0]
            starts = [g.inverse(puck - (g.contact + self.settings.standoff) * u, s) for s in signs]
            self._plan_for, self._plan = key, (signs, starts, self.planner.wave(puck, starts))
        return self._plan

    def orbit_target(self, puck, u, n, along: float, across: float, elbow: float) -> np.ndarray | None:
        """The fingertip's next point round the puck (``approach: orbit``), or None where
        neither way round keeps the links clear with the elbow on its side."""
        g, geo = self.gains, self.geometry
        start = geo.contact + self.settings.standoff  # the push's start, behind the puck
        radius = geo.contact + g.orbit
        angle, dist = math.atan2(across, along), math.hypot(along, across)
        # behind the puck is at +pi or -pi: the shorter arc first
        for end in sorted((math.pi, -math.pi), key=lambda e: abs(e - angle)):
            if not self._arc_clear(puck, u, n, angle, max(dist, radius), end, start, elbow):
                continue
            left = end - angle
            if abs(left) <= g.orbit_arc:
                return puck - start * u
            a = angle + math.copysign(g.orbit_arc, left)
            r = max(radius, dist - g.orbit_spiral)
            return puck + r * (math.cos(a) * u + math.sin(a) * n)
        return None

    def _arc_clear(self, puck, u, n, angle: float, dist: float, end: float, start: float, elbow: float) -> bool:
        """Whether the links stay ``margin`` clear of the puck, and the fingertip within reach,
        along the arc from ``angle`` at ``dist`` to ``end`` at the push's start."""
        geo, k = self.geometry, self.gains.orbit_checks
        inner, outer = abs(geo.links[0] - geo.links[1]) + 1e-3, sum(geo.links) - 1e-3
        for i in range(1, k + 1):
            a = angle + (end - angle) * i / k
            p = puck + (dist + (start - dist) * i / k) * (math.cos(a) * u + math.sin(a) * n)
            if not inner < math.hypot(*p) < outer:
                return False
            upper, fore = geo.clearance(*geo.inverse(p, elbow), puck)
            if min(float(upper), float(fore)) < self.gains.margin:
                return False
        return True

    def __call__(self, positions, velocities, goal, points=None) -> np.ndarray:
        if points is None or self.point not in points:
            raise ValueError(f"the push expert needs the puck's position (points[{self.point!r}])")
        q = np.asarray(positions, np.float64)[:2]
        qdot = np.asarray(velocities, np.float64)[:2]
        puck = np.asarray(points[self.point], np.float64)[:2]
        goal = np.asarray(goal, np.float64)[:2]
        g, geo = self.gains, self.geometry
        to_goal = goal - puck
        d = math.hypot(*to_goal)
        if d < self.hold:
            return self.torque(q, qdot, None)
        u = to_goal / d
        n = np.array([-u[1], u[0]])
        _, tip = geo.elbow_and_tip(q[0], q[1])
        rel = tip - puck
        along, across = float(rel @ u), float(rel @ n)
        near = math.hypot(along, across) < geo.contact + self.settings.standoff + g.align
        elbow_side = 1.0 if wrap(q[1]) >= 0 else -1.0
        if near and along < -0.5 * geo.contact and (abs(across) < g.align or d < g.nudge):
            # off the line, a pushed disc runs off it (away from the fingertip): aim past the line
            # to bring it back, and push the softer the further off. Close to the goal the line
            # turns with every millimetre: push the puck the way it faces, as far as it nears
            # the goal (a nudge), instead of going round
            if abs(across) < g.align:
                depth = min(g.push_gain * d, g.push_depth) * (1.0 - abs(across) / g.align)
                target = puck + (depth - geo.contact) * u - g.steer * across * n
            else:
                facing = -rel / math.hypot(*rel)
                target = tip + max(float(to_goal @ facing), 0.0) * facing
            ahead = target - tip
            if math.hypot(*ahead) > g.step:
                target = tip + ahead * (g.step / math.hypot(*ahead))
            return self.torque(q, qdot, geo.inverse(target, elbow_side))
        signs, starts, wave = self.plan(puck, goal, u)
        if self.settings.approach == "orbit" and elbow_side in signs:
            target = self.orbit_target(puck, u, n, along, across, elbow_side)
            if target is not None:
                return self.torque(q, qdot, geo.inverse(target, elbow_side))
        q_star = self.planner.toward(q, wave, g.lookahead)
        if q_star is None:  # at a start's cell (or no way round): straight to the nearest start
            q_star = min(starts, key=lambda s: float(np.abs(wrap(np.asarray(s) - q)).sum()))
        return self.torque(q, qdot, q_star)

    def torque(self, q, qdot, q_star) -> np.ndarray:
        g = self.gains
        action = -g.kd * qdot if q_star is None else g.kp * wrap(np.asarray(q_star) - q) - g.kd * qdot
        return np.clip(action, -1.0, 1.0).astype(np.float32)
