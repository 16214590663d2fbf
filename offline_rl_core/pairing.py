"""Pairing a joint state with its target and fingertip by stamp (no ROS).

A policy (or the corrector) must answer each state with the observation the training
data had: the state, the target of the same instant and, where the source publishes it,
the fingertip of the same instant. They arrive on separate topics in any order.

- Target: once a target has carried a state's stamp (the sim stamps each target with
  its state), the source is known to *co-stamp*, and a state waits for the target with
  its stamp; so the first state of an episode is never answered with the previous
  episode's target. Otherwise (another arm) the latest target is used.
- Fingertip: once any fingertip has been heard, a state also waits for the fingertip
  with its stamp; without one the observation uses forward kinematics.

Only the latest state waits: a newer state replaces it (a controller wants the newest).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Paired:
    state: object  # whatever the caller passed with the state (the message)
    stamp: int
    target_xy: np.ndarray
    fingertip_xy: np.ndarray | None  # None: none published; use forward kinematics


class StatePairing:
    def __init__(self, use_fingertip: bool = True):
        self.use_fingertip = use_fingertip
        self.target_stamp: int | None = None
        self.target_xy: np.ndarray | None = None
        self.co_stamped = False
        self.fingertip_stamp: int | None = None
        self.fingertip_xy: np.ndarray | None = None
        self.pending: tuple[int, object] | None = None

    def on_target(self, stamp: int, xy) -> Paired | None:
        self.target_stamp, self.target_xy = stamp, np.asarray(xy, np.float64)[:2].copy()
        if self.pending is not None and self.pending[0] == stamp:
            self.co_stamped = True
        return self._ready()

    def on_fingertip(self, stamp: int, xy) -> Paired | None:
        if not self.use_fingertip:
            return None
        self.fingertip_stamp, self.fingertip_xy = stamp, np.asarray(xy, np.float64)[:2].copy()
        return self._ready()

    def on_state(self, stamp: int, state) -> Paired | None:
        if self.target_xy is not None and self.target_stamp == stamp:
            self.co_stamped = True
        self.pending = (stamp, state)
        return self._ready()

    def _ready(self) -> Paired | None:
        """The waiting state with what it pairs with, once all has arrived."""
        if self.pending is None or self.target_xy is None:
            return None
        stamp, state = self.pending
        if self.co_stamped and self.target_stamp != stamp:
            return None  # its target is still on the way
        if self.fingertip_xy is not None and self.fingertip_stamp != stamp:
            return None  # the source publishes fingertips: wait for this state's
        self.pending = None
        return Paired(state, stamp, self.target_xy, self.fingertip_xy if self.fingertip_stamp == stamp else None)
