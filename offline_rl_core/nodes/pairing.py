"""Pairing a joint state with its goal and tracked points by stamp, and judging stamps (no ROS).

A policy (or the corrector) must answer each state with the observation the training
data had: the state, the goal of the same instant and, where the source publishes them,
the tracked points (pusher_reach: the fingertip) of the same instant. They arrive on
separate topics in any order.

- Goal: once a goal has carried a state's stamp (the sim stamps each target with its
  state), the source is known to *co-stamp*, and a state waits for the goal with its
  stamp; so the first state of an episode is never answered with the previous episode's
  goal. Otherwise (another arm) the latest goal is used.
- A tracked point: once one has carried the stamp of a state (waiting or recent), its
  topic co-stamps and a state waits for its point too; a point topic that does not
  co-stamp gives its latest point; a point never heard is left out of the pairing (the
  observation takes it from forward kinematics).
- The last ``KEEP`` goals and points are remembered by stamp, so one that comes out of
  order, or a stray one with a wild stamp, never displaces the one a state needs.

Only the latest state waits: a newer state replaces it (a controller wants the newest).

Stamps (:func:`check_stamp`, :class:`StampOrder`): a stamp that is no valid time is
refused outright. A state older than the newest one admitted is *stale* and one far
ahead (more than ``jump_s``) is a *future* stamp: both are refused, unless the next
state continues from it (the same stamp again, or a little later), which means the
source's clock really moved (a restarted sim, a new start_time) and the pairing follows
it. So one stray stamp, or a burst of them, never wedges a node on a wrong timeline:
a real source (the lockstep sim republishes a state until it is answered; the realtime
sim sends the next one 20 ms later) loses at most one state to it.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from ..common.rejections import Rejection

NS_PER_S = 1_000_000_000
KEEP = 32  # goals, points and state stamps remembered (the latest arrivals)
# Largest forward step of a real source's stamps taken without confirmation: a lockstep
# episode that ends early jumps to the next episode's first tick, up to 2 s of sim time.
JUMP_S = 5.0


@dataclass
class Paired:
    state: object  # whatever the caller passed with the state (the message)
    stamp: int
    goal: np.ndarray
    points: dict[str, np.ndarray] = field(default_factory=dict)  # the tracked points heard for it

    @property
    def target_xy(self) -> np.ndarray:
        """pusher_reach's name for the goal."""
        return self.goal

    @property
    def fingertip_xy(self) -> np.ndarray | None:
        """pusher_reach's fingertip, or None when none was published (forward kinematics)."""
        return self.points.get("fingertip")


def check_stamp(sec: int, nanosec: int) -> Rejection | None:
    """Why a header stamp (``builtin_interfaces/Time``) is no valid time, or None."""
    if sec < 0 or not 0 <= nanosec < NS_PER_S:
        return Rejection("bad stamp", f"stamp {sec} s {nanosec} ns is not a valid time")
    return None


class StampOrder:
    """The stamps of one stream: refuses stale and far-future ones that nothing confirms."""

    def __init__(self, jump_s: float = JUMP_S):
        self.jump_ns = int(jump_s * NS_PER_S)
        self.newest: int | None = None  # the newest stamp admitted
        self.candidate: int | None = None  # the last stamp refused, until the next one confirms it

    def check(self, stamp: int) -> Rejection | None:
        """Admit ``stamp`` (None), or say why not."""
        if self.newest is None or self.newest <= stamp <= self.newest + self.jump_ns or self._confirms(stamp):
            self.newest, self.candidate = stamp, None  # never behind the newest, unless confirmed
            return None
        self.candidate = stamp
        if stamp < self.newest:
            return Rejection("stale stamp", f"stamp {stamp / NS_PER_S:.3f} s is older than the newest, "
                                            f"{self.newest / NS_PER_S:.3f} s")
        return Rejection("future stamp", f"stamp {stamp / NS_PER_S:.3f} s jumps more than "
                                         f"{self.jump_ns / NS_PER_S:g} s ahead of {self.newest / NS_PER_S:.3f} s")

    def _confirms(self, stamp: int) -> bool:
        return self.candidate is not None and self.candidate <= stamp <= self.candidate + self.jump_ns


def _remember(store: OrderedDict, stamp: int, value) -> None:
    store[stamp] = value
    store.move_to_end(stamp)
    while len(store) > KEEP:
        store.popitem(last=False)


class _Stream:
    """The latest values of one topic by stamp, and whether its stamps are the states'."""

    def __init__(self):
        self.by_stamp: OrderedDict[int, np.ndarray] = OrderedDict()
        self.latest: np.ndarray | None = None
        self.co_stamped = False

    def add(self, stamp: int, value) -> None:
        self.latest = np.array(value, np.float64).reshape(-1)
        _remember(self.by_stamp, stamp, self.latest)

    def value_for(self, stamp: int) -> np.ndarray | None:
        return self.by_stamp.get(stamp) if self.co_stamped else self.latest


class StatePairing:
    """``points``: the names of the tracked points whose topics are paired (pusher_reach:
    the fingertip); ``required``: those among them a state always waits for, heard or not
    (no kinematics stands in for them)."""

    def __init__(self, use_fingertip: bool = True, jump_s: float = JUMP_S, points: tuple[str, ...] | None = None,
                 required: tuple[str, ...] = ()):
        self.order = StampOrder(jump_s)
        self.goal = _Stream()
        self.points = {name: _Stream() for name in (points if points is not None else
                                                     ("fingertip",) if use_fingertip else ())}
        self.required = set(required)
        self.recent_states: OrderedDict[int, None] = OrderedDict()  # stamps of the latest states
        self.pending: tuple[int, object] | None = None

    @property
    def co_stamped(self) -> bool:
        return self.goal.co_stamped

    def admit(self, stamp: int) -> Rejection | None:
        """Judge a state's stamp before ``on_state`` (stale and future ones are refused)."""
        return self.order.check(stamp)

    def on_goal(self, stamp: int, value) -> Paired | None:
        self.goal.add(stamp, value)
        if self.pending is not None and self.pending[0] == stamp:
            self.goal.co_stamped = True
        return self._ready()

    def on_point(self, name: str, stamp: int, value) -> Paired | None:
        stream = self.points.get(name)
        if stream is None:
            return None
        stream.add(stamp, value)
        if stamp in self.recent_states:
            stream.co_stamped = True
        return self._ready()

    def on_target(self, stamp: int, xy) -> Paired | None:
        """pusher_reach's goal: a planar target."""
        return self.on_goal(stamp, np.asarray(xy, np.float64)[:2])

    def on_fingertip(self, stamp: int, xy) -> Paired | None:
        return self.on_point("fingertip", stamp, np.asarray(xy, np.float64)[:2])

    def on_state(self, stamp: int, state) -> Paired | None:
        if stamp in self.goal.by_stamp:
            self.goal.co_stamped = True
        for stream in self.points.values():
            if stamp in stream.by_stamp:
                stream.co_stamped = True
        _remember(self.recent_states, stamp, None)
        self.pending = (stamp, state)
        return self._ready()

    def _ready(self) -> Paired | None:
        """The waiting state with what it pairs with, once all has arrived."""
        if self.pending is None or self.goal.latest is None:
            return None
        stamp, state = self.pending
        goal = self.goal.value_for(stamp)
        if goal is None:
            return None  # its goal is still on the way
        points = {}
        for name, stream in self.points.items():
            if stream.latest is None:
                if name in self.required:
                    return None  # nothing stands in for it: wait until it is heard
                continue  # never heard: kinematics
            value = stream.value_for(stamp)
            if value is None:
                return None  # the source publishes this point: wait for this state's
            points[name] = value
        self.pending = None
        return Paired(state, stamp, goal, points)


def check_answer_stamp(stamp: int, current: int) -> Rejection | None:
    """A lockstep command must answer the current state: an older stamp is stale (a late
    duplicate, or a republished state answered twice), a newer one is from the future."""
    if stamp == current:
        return None
    if stamp < current:
        return Rejection("stale stamp", f"answers {stamp / NS_PER_S:.3f} s, the current state is "
                                        f"{current / NS_PER_S:.3f} s")
    return Rejection("future stamp", f"answers {stamp / NS_PER_S:.3f} s, ahead of the current state at "
                                     f"{current / NS_PER_S:.3f} s")
