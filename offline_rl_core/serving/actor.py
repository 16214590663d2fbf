"""The acting side of the HIL-SERL stage, without ROS: which weights act, how they explore,
and when a state must wait for newer weights.

The policy node holds one :class:`Actor`. Weights arrive as checkpoints (a file it
watches, or the online learner's weights messages); :meth:`Actor.offer` keeps the newest
version. By default the actor is deterministic (``tanh(mean)``, what evaluation scores);
with ``explore`` it samples the learner's Gaussian, ``tanh(mean + std * eps)``, the noise
of state n drawn from (seed, n) alone: the same session gives the same actions, also
where a state went unanswered (a person's takeover moved the arm on first).

Paced (``paced_every`` = the learner's ``publish_every``): state n of the session (counted
by distinct stamps) is answered only with weights version ``n // paced_every`` or newer,
the version the learner cuts once it has trained on every transition before it. The
learner can never be further ahead than that (it has not seen later transitions), so a
paced actor acts on exactly that version: in lockstep the sim cannot outrun the learner,
and a run is reproducible whatever the speed of either.
"""

from __future__ import annotations

import numpy as np

from .policy import LoadedPolicy
from ..common.rejections import Rejection

# How far past the acting version a weights message may be: the learner cuts one version
# at a time, and a policy node reads every one in order unless DDS dropped some.
MAX_VERSION_STEP = 16


class Actor:
    def __init__(self, policy: LoadedPolicy, explore: bool = False, seed: int = 0, paced_every: int = 0):
        self.policy = policy
        self.explore = explore
        self.seed = int(seed)
        self.paced_every = int(paced_every)
        self.states = 0  # distinct states seen this session
        self.last_stamp: int | None = None
        self.answered: tuple[int, np.ndarray] | None = None  # (stamp, action) of the last answer

    @property
    def version(self) -> int:
        return self.policy.weights_version

    def offer(self, policy: LoadedPolicy) -> bool:
        """Take ``policy`` if it is a newer weights version than the one acting, the
        learner's first version, or unversioned (a checkpoint file replaced by hand);
        returns whether it now acts."""
        if policy.versioned and self.policy.versioned and policy.weights_version <= self.version:
            return False
        self.policy = policy
        return True

    def offer_weights(self, policy: LoadedPolicy) -> tuple[bool, Rejection | None]:
        """Take a weights message's policy (already verified as this session's learner's):
        only a versioned one, and only one of the next ``MAX_VERSION_STEP`` versions after
        the one acting, so no message, however it came by its signature, can put a version
        so far ahead that every later one of the real learner is refused. The first versioned
        weights after a checkpoint file are taken whatever their version (a policy node may
        start late in a session). Returns (taken, why refused); an older or equal version is
        neither taken nor refused: a learner restarted from its last resume point repeats
        versions the node has."""
        if not policy.versioned:
            return False, Rejection("weights version", "unversioned weights are not taken from the topic")
        if self.policy.versioned:
            if policy.weights_version <= self.version:
                return False, None
            if policy.weights_version > self.version + MAX_VERSION_STEP:
                return False, Rejection("weights version", f"weights version {policy.weights_version} is more than "
                                                           f"{MAX_VERSION_STEP} past the acting {self.version}")
        self.policy = policy
        return True, None

    def see(self, stamp: int) -> None:
        """Count a state (once per stamp: a republished state is the same state)."""
        if stamp != self.last_stamp:
            if self.last_stamp is not None:
                self.states += 1
            self.last_stamp = stamp

    def required_version(self) -> int:
        return self.states // self.paced_every if self.paced_every else 0

    def ready(self) -> bool:
        """Whether the current state may be answered with the weights held. Paced, only
        the learner's own weights count: the checkpoint the node started from (the prior)
        has no exploration std, and acting on it until the learner's first version arrives
        would make the session depend on how fast that message came."""
        if not self.paced_every:
            return True
        return self.policy.versioned and self.version >= self.required_version()

    def act(self, obs: np.ndarray, stamp: int | None = None) -> np.ndarray:
        """The action for the state ``obs`` stamped ``stamp``: in [-1, 1] (a non-finite one
        is returned as is for the caller to refuse). A state answered before (the sim
        republishes one whose command was lost) gets the same action again: one draw of
        exploration noise per state."""
        if stamp is not None and self.answered is not None and self.answered[0] == stamp:
            return self.answered[1]
        if self.explore:
            action = self.policy.sample(obs, np.random.default_rng([self.seed, 11, self.states]))
        else:
            action = self.policy.act(obs)
        if stamp is not None:
            self.answered = (stamp, action)
        return action

    def answer(self, obs: np.ndarray, stamp: int | None = None) -> tuple[np.ndarray | None, Rejection | None]:
        """``act`` as a server answers: the action clipped into [-1, 1], or (None, why not).
        One state the policy fails on, or answers with NaN, is refused and counted by the
        caller; it never ends the node serving every other state."""
        try:
            action = self.act(obs, stamp)
        except Exception as exc:  # noqa: BLE001 - whatever the policy raised, the next state is answered
            return None, Rejection("policy error", f"the {self.policy.algorithm} policy failed on this state "
                                                   f"({type(exc).__name__}: {str(exc)[:120]}); none sent")
        if not np.all(np.isfinite(action)):
            return None, Rejection("non-finite action", "the policy's action for this state is not finite; none sent")
        return np.clip(action, -1.0, 1.0), None
