"""Pairing a joint state with its target and fingertip by stamp, and judging stamps (no ROS).

A policy (or the corrector) must answer each state with the observation the training
data had: the state, the target of the same instant and, where the source publishes it,
the fingertip of the same instant. They arrive on separate topics in any order.

- Target: once a target has carried a state's stamp (the sim stamps each target with
  its state), the source is known to *co-stamp*, and a state waits for the target with
  its stamp; so the first state of an episode is never answered with the previous
  episode's target. Otherwise (another arm) the latest target is used.
- Fingertip: once any fingertip has been heard, a state also waits for the fingertip
  with its stamp; without one the observation uses forward kinematics.
- The last ``KEEP`` targets and fingertips are remembered by stamp, so one that comes
  out of order, or a stray one with a wild stamp, never displaces the one a state needs.

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
from dataclasses import dataclass

import numpy as np

from ..common.rejections import Rejection

NS_PER_S = 1_000_000_000
KEEP = 32  # targets and fingertips remembered by stamp (the latest arrivals)
# Largest forward step of a real source's stamps taken without confirmation: a lockstep
# episode that ends early jumps to the next episode's first tick, up to 2 s of sim time.
JUMP_S = 5.0


@dataclass
class Paired:
    state: object  # whatever the caller passed with the state (the message)
    stamp: int
    target_xy: np.ndarray
    fingertip_xy: np.ndarray | None  # None: none published; use forward kinematics


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


class StatePairing:
    def __init__(self, use_fingertip: bool = True, jump_s: float = JUMP_S):
        self.use_fingertip = use_fingertip
        self.order = StampOrder(jump_s)
        self.targets: OrderedDict[int, np.ndarray] = OrderedDict()
        self.latest_target: np.ndarray | None = None
        self.co_stamped = False
        self.fingertips: OrderedDict[int, np.ndarray] = OrderedDict()
        self.pending: tuple[int, object] | None = None

    def admit(self, stamp: int) -> Rejection | None:
        """Judge a state's stamp before ``on_state`` (stale and future ones are refused)."""
        return self.order.check(stamp)

    def on_target(self, stamp: int, xy) -> Paired | None:
        self.latest_target = np.asarray(xy, np.float64)[:2].copy()
        _remember(self.targets, stamp, self.latest_target)
        if self.pending is not None and self.pending[0] == stamp:
            self.co_stamped = True
        return self._ready()

    def on_fingertip(self, stamp: int, xy) -> Paired | None:
        if not self.use_fingertip:
            return None
        _remember(self.fingertips, stamp, np.asarray(xy, np.float64)[:2].copy())
        return self._ready()

    def on_state(self, stamp: int, state) -> Paired | None:
        if stamp in self.targets:
            self.co_stamped = True
        self.pending = (stamp, state)
        return self._ready()

    def _ready(self) -> Paired | None:
        """The waiting state with what it pairs with, once all has arrived."""
        if self.pending is None or self.latest_target is None:
            return None
        stamp, state = self.pending
        target = self.targets.get(stamp) if self.co_stamped else self.latest_target
        if target is None:
            return None  # its target is still on the way
        fingertip = self.fingertips.get(stamp)
        if self.fingertips and fingertip is None:
            return None  # the source publishes fingertips: wait for this state's
        self.pending = None
        return Paired(state, stamp, target, fingertip)


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
