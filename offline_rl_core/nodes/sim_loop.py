"""The sim node's protocol as a plain class: episodes, sim time, stepping, results (no ROS).

The arm is any task's env (``task.envs.make_env``): pusher_reach by default.

``realtime``: ``tick()`` steps the arm with the latest command held (zero-order hold, as a
motor driver does); the node calls it from a timer at the task's control period.
``lockstep``: ``command(stamp, action, source)`` steps the arm only when ``stamp`` is the
current state's, so data collection and evaluation run as fast as the loop allows and
are reproducible; any other stamp answers an older or a republished state and is stale.
A command without a stamp (a controller's Float64MultiArray has no header) cannot name the
state it answers: ``command_unstamped`` takes the first one after the current state was
published (``published()``) as its answer, and refuses it once commands with stamps have
come (they pair exactly; taking both would step twice per state).

Safety (realtime): every valid command feeds a :class:`~.watchdog.CommandWatchdog`; a tick
that finds the commands silent for the task's ``command_timeout``, or the e-stop engaged
(``estop``, a :class:`~.estop.EStopLatch` the node feeds), steps with the task's safe command
instead of the held one (zero effort or velocity, or the position held), and the row records
the action that was applied. Lockstep needs neither: the arm steps only on a command.

Sim time: every state carries ``start_ns + tick * control_period``. In lockstep, step ``s``
of episode ``e`` is tick ``e * max_steps + s`` (an episode owns max_steps ticks however it
ends), so a state's stamp says which episode and step it is; in realtime the tick counts
physics steps. The node publishes it on /clock and stamps every message with it.

Every state handed out is one a command applies to: the state after an episode's last
step is not (it is the ``next_obs`` of the final transition); the next episode's first
state follows the final transition.

A person's label (``label(success, episode)``, from ``episode_label``: data.episode_labels)
of the current episode ends it at its next step, in either mode, as its time limit would:
that transition is the episode's last, scored by the task's rule with the label as the
state's success (a success: ``terminated``, with the task's bonus; a failure: ``truncated``,
the person stopped it), and the next episode's first state follows. A label without an
episode is of the episode of the last transition handed out, as the bag's reader attributes
it: one pressed just after an episode ended labels that one and ends nothing. The episode's
result (``summary``) stays the simulator's success; ``labelled`` counts the episodes a label
ended, ``labels_against_simulator`` those whose label the simulator contradicts.

``steps`` caps the run's environment steps however its episodes end (early, on success or
a label): the step that reaches it ends its episode, truncated, and the run is finished.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..common.rejections import Rejection
from ..data.transitions import Layout, SOURCE_POLICY
from ..task import features
from ..task.envs import make_env
from ..task.pusher_reach import CONTROL_HZ, MAX_STEPS
from ..task.spec import JOINT_STATE, TaskSpec, load_task
from .estop import EStopLatch
from .state_limits import StateLimits
from .watchdog import CommandWatchdog, safe_action

TICK_NS = 1_000_000_000 // CONTROL_HZ  # pusher_reach's 20 ms (a task's own: SimLoop.tick_ns)
TICKS_PER_EPISODE = MAX_STEPS  # lockstep: one tick per state an episode can have
MODES = ("realtime", "lockstep")
# builtin_interfaces/Time.sec is an int32: a later start wraps to negative stamps that every
# reader refuses. A year short of 2**31 s (Jan 2038) leaves a run a year of stamps.
MAX_START_TIME_S = 2**31 - 1 - 365 * 24 * 3600


@dataclass
class ArmState:
    """One state of the arm, as the node publishes it."""

    stamp_ns: int
    position: np.ndarray  # the state joints' positions (rad, m)
    velocity: np.ndarray  # rad/s, m/s
    torque: np.ndarray  # N·m (N) the actuators applied at the state joints in the last step
    target: np.ndarray | None  # m (x, y, z): a Cartesian goal's point
    goal: np.ndarray = None  # the task's goal vector (its axes, or a joint-space goal's positions)
    points: dict = field(default_factory=dict)  # tracked point name -> x, y, z (m)

    @property
    def fingertip(self) -> np.ndarray | None:
        return self.points.get("fingertip")


@dataclass
class Step:
    """What one step produced: the transition row, and the next state to publish (None
    after an episode's last step: the next episode's first state is in ``new_episode``)."""

    transition: np.ndarray  # float32[layout.width], the task's transition layout
    next_state: ArmState | None
    episode_over: bool
    new_episode: ArmState | None = None  # the next episode's first state (None once finished)


class SimLoop:
    def __init__(self, mode: str = "realtime", seed: int = 0, episodes: int = 0, terminate_on_success: bool = False,
                 start_ns: int = 0, task: TaskSpec | str | None = None, estop: EStopLatch | None = None,
                 steps: int = 0):
        if mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
        self.mode = mode
        self.seed = seed
        self.max_episodes = episodes  # 0: run until stopped
        # 0: no cap; else the steps of the run, however its episodes end (a budget of
        # environment steps where episodes end early: the step that reaches it ends its episode)
        self.max_steps = steps
        self.steps_taken = 0
        self.start_ns = int(start_ns)
        self.task = load_task(task)
        self.env = make_env(self.task, terminate_on_success or self.task.reward.terminate_on_success)
        self.layout = Layout(self.task.obs_dim, self.task.act_dim)
        self.tick_ns = round(self.task.control_period * 1e9)
        self.ticks_per_episode = self.task.episodes.max_steps
        self.stamped_commands = False  # lockstep: a command with a stamp has come (see command_unstamped)
        self.answerable = False  # lockstep: the current state is published and not yet answered
        self.episode = 0  # index of the current episode; it resets with seed + episode
        self.ticks = 0  # realtime: physics steps so far
        self.results: list[tuple[bool, float, float]] = []  # (success, final distance, return) per episode
        self.abandoned = 0  # episodes cut short by a reset: counted as failures in the success rate
        self.ep_return = 0.0
        self.obs: np.ndarray | None = None
        self.held_action = np.zeros(self.task.act_dim, np.float32)
        self.held_source = SOURCE_POLICY
        self.current: ArmState | None = None
        self.watchdog = CommandWatchdog(self.task.command_timeout)
        self.estop = estop if estop is not None else EStopLatch()  # a node's own latch, made before the env
        self.safe_steps = 0  # realtime ticks that applied the safe command
        self.state_limits = StateLimits(self.task)  # effort interface: soft limits on the measured state
        self.limit_steps = 0  # realtime ticks whose held command pushed a joint further out: the safe one applied
        self.label_of_current: bool | None = None  # a person's label of the current episode: its next step ends it
        self.last_stepped: int | None = None  # the episode of the last transition handed out
        self.labelled = 0  # episodes a label ended
        self.labels_against_simulator = 0  # ... of them, those whose label is not the simulator's success

    # ------------------------------------------------------------ episodes
    @property
    def finished(self) -> bool:
        return (bool(self.max_episodes) and len(self.results) >= self.max_episodes) or \
            (bool(self.max_steps) and self.steps_taken >= self.max_steps)

    def start_episode(self) -> ArmState:
        """Reset for the current episode; its first state."""
        self.obs = self.env.reset(seed=self.seed + self.episode)
        self.ep_return = 0.0
        self.label_of_current = None
        return self._snapshot()

    def label(self, success: bool, episode: int | None = None) -> tuple[int | None, Rejection | None]:
        """A person's label of ``episode`` (None: of the episode of the last transition): the
        episode it labels, and whether it ends it (it does when it is the current one); or
        (None, why) for a label that names no episode there is or was."""
        if self.finished:
            return None, None
        target = self.last_stepped if episode is None else episode
        if target is None:
            return None, Rejection("bad label", "a label before any step: which episode it labels cannot be told "
                                                "(give it an episode number)")
        if target > self.episode:
            return None, Rejection("bad label", f"a label of episode {target}, which has not started (the current "
                                                f"one is {self.episode})")
        if target == self.episode:
            self.label_of_current = bool(success)  # a later label replaces it: the person changed their mind
        return target, None

    def reset(self) -> ArmState:
        """Abandon the episode and start the next (the reset service): the abandoned one is
        counted, so resets cannot hide failing episodes from the success rate."""
        self.abandoned += 1
        self.episode += 1
        return self.start_episode()

    def stamp_ns(self) -> int:
        tick = self.episode * self.ticks_per_episode + self.env.steps if self.mode == "lockstep" else self.ticks
        return self.start_ns + tick * self.tick_ns

    def _snapshot(self) -> ArmState:
        env = self.env
        cartesian = self.task.goal.type != JOINT_STATE
        self.current = ArmState(self.stamp_ns(), np.array(env.joint_positions, np.float64),
                                np.array(env.joint_velocities, np.float64),
                                np.array(env.joint_efforts, np.float64),
                                np.array(env.goal_position, np.float64) if cartesian else None,
                                np.array(env.goal, np.float64),
                                {name: np.array(p, np.float64) for name, p in env.point_positions().items()})
        self.answerable = False
        return self.current

    def published(self) -> None:
        """The node has published the current state: a headerless command may answer it now."""
        self.answerable = True

    # ------------------------------------------------------------ stepping
    def command(self, stamp_ns: int | None, action: np.ndarray, source: int, now: float | None = None) -> Step | None:
        """A command for the state stamped ``stamp_ns`` (lockstep), or the one to hold (realtime,
        fed to the watchdog at ``now``, seconds on a steady clock)."""
        if self.finished:
            return None
        if self.mode == "realtime":
            self.hold(action, source, now)
            return None
        self.stamped_commands = True
        if stamp_ns != self.current.stamp_ns:
            return None  # answers an older (or republished, already answered) state: stale
        return self._step(action, source)

    def command_unstamped(self, action: np.ndarray, source: int,
                          now: float | None = None) -> tuple[Step | None, Rejection | None]:
        """A command without a stamp: held (realtime), or in lockstep the answer to the
        current state if it is the first since that state was published; else (None, why)."""
        if self.finished:
            return None, None
        if self.mode == "realtime":
            self.hold(action, source, now)
            return None, None
        if self.stamped_commands:
            return None, Rejection("unpaired", "a command without a stamp, while commands with stamps answer "
                                               "the states (lockstep pairs those exactly)")
        if not self.answerable:
            return None, Rejection("unpaired", "a command without a stamp, but the current state is already "
                                               "answered or not yet published (lockstep takes the first after "
                                               "each state)")
        return self._step(action, source), None

    def hold(self, action: np.ndarray, source: int, now: float | None) -> None:
        self.held_action, self.held_source = action, source
        if now is not None:
            self.watchdog.fed(now)

    def safe(self, now: float | None) -> bool:
        """Whether a realtime tick at ``now`` applies the safe command (e-stop, silent commands)."""
        silent = now is not None and self.watchdog.check(now)
        return self.estop.engaged or silent

    def beyond_state_limits(self, action: np.ndarray) -> Rejection | None:
        """Why ``action`` may not be applied where the arm is now (it pushes a joint further
        beyond the task's position or velocity limits); None where it may."""
        return self.state_limits.check(action, self.env.joint_positions, self.env.joint_velocities)

    def safe_action(self) -> np.ndarray:
        """The task's safe command as an action: zero effort or velocity, or the position now."""
        return safe_action(self.task, self.env.joint_positions)

    def tick(self, now: float | None = None) -> Step | None:
        """Realtime: one step with the held command, or the safe one (see ``safe``)."""
        if self.finished or self.mode != "realtime":
            return None
        self.ticks += 1
        if self.safe(now):
            self.safe_steps += 1
            return self._step(self.safe_action(), self.held_source)
        if self.beyond_state_limits(self.held_action) is not None:  # taken inside, but the arm has gone out since
            self.limit_steps += 1
            return self._step(self.safe_action(), self.held_source)
        return self._step(self.held_action, self.held_source)

    def faults(self) -> dict:
        """The latched faults, as ``~/status`` shows them."""
        watchdog = self.watchdog.fault()
        return {"watchdog": watchdog} if watchdog else {}

    def reset_faults(self) -> None:
        self.watchdog.reset()

    def estop_engaged(self) -> None:
        """The e-stop engaged: the command held before it is dropped, so a reset does not
        bring it back; the safe command holds until a fresh command comes after the reset."""
        self.held_action = self.safe_action()
        self.watchdog.disarm()

    def _step(self, action: np.ndarray, source: int) -> Step:
        obs, step_index, success_before = self.obs, self.env.steps, bool(self.env.success)
        next_obs, reward, done, info = self.env.step(action)
        simulator_success = bool(info["success"])
        if self.label_of_current is not None:
            reward, info = self._scored_by_label(success_before, self.label_of_current)
            done = True
        self.steps_taken += 1
        if self.max_steps and self.steps_taken >= self.max_steps and not done:
            info, done = {**info, "truncated": True}, True  # the run's budget: cut as a time limit cuts
        at = self.layout.slices
        row = np.empty(self.layout.width, np.float32)
        row[at["obs"]] = obs
        row[at["action"]] = action
        row[at["reward"]] = reward
        row[at["next_obs"]] = next_obs
        row[at["terminated"]] = info["terminated"]
        row[at["truncated"]] = info["truncated"]
        row[at["success"]] = info["success"]
        row[at["episode"]] = self.episode
        row[at["step"]] = step_index
        row[at["source"]] = source
        self.ep_return += reward
        self.obs = next_obs
        self.last_stepped = self.episode
        if not done:
            return Step(row, self._snapshot(), False)
        if self.label_of_current is not None:
            self.labelled += 1
            self.labels_against_simulator += self.label_of_current != simulator_success
        self.results.append((simulator_success, float(info["dist"]), self.ep_return))
        self.episode += 1
        return Step(row, None, True, None if self.finished else self.start_episode())

    def _scored_by_label(self, success_before: bool, success: bool) -> tuple[float, dict]:
        """The step just taken, scored by the task's rule with the label as its success, and
        ending the episode: (reward, info)."""
        env = self.env
        vectors = {name: v[None] for name, v in env.vectors().items()}
        # a failure label overrides a success the simulator latched before: the person's word is the episode's
        score = features.score(self.task, env.joint_positions[None], vectors, [env.steps], [success_before and success],
                               terminate_on_success=True, success_now=[success])
        terminated = bool(score.terminated[0])
        return float(score.reward[0]), {"terminated": terminated, "truncated": not terminated,
                                        "success": bool(score.success[0]), "dist": float(score.dist[0])}

    # ------------------------------------------------------------ results
    def summary(self) -> dict:
        """Episodes run to their end, and ``abandoned`` ones (reset before it); the success rate
        is over both, the distance and return over those that ended."""
        n = len(self.results)
        extra = {"abandoned": self.abandoned} if self.abandoned else {}
        if self.labelled:
            extra.update(labelled=self.labelled, labels_against_simulator=self.labels_against_simulator)
        if n == 0:
            return {"episodes": 0, "success_rate": 0.0, "mean_final_dist": None, "mean_return": None, **extra}
        success, dist, ret = (np.array(col, np.float64) for col in zip(*self.results))
        return {"episodes": n, "success_rate": float(success.sum() / (n + self.abandoned)),
                "mean_final_dist": float(dist.mean()), "mean_return": float(ret.mean()), **extra}


class TickTiming:
    """Realtime tick periods in running sums (a sim that runs for days keeps no list).

    A missed step is a gap over 1.5 periods (a gap of k periods missed k - 1 steps).
    """

    def __init__(self, period_s: float = 1.0 / CONTROL_HZ):
        self.period_ms = period_s * 1000.0
        self.ticks = 0
        self.last: float | None = None
        self.sum_ms = self.sum_sq_ms = self.max_ms = 0.0
        self.missed = 0

    def tick(self, now_s: float) -> None:
        if self.last is not None:
            gap = (now_s - self.last) * 1000.0
            self.sum_ms += gap
            self.sum_sq_ms += gap * gap
            self.max_ms = max(self.max_ms, gap)
            self.missed += max(int(np.floor(gap / self.period_ms + 0.5)) - 1, 0)
        self.last = now_s
        self.ticks += 1

    def report(self) -> str | None:
        gaps = self.ticks - 1
        if gaps < 2:
            return None
        mean = self.sum_ms / gaps
        std = float(np.sqrt(max(self.sum_sq_ms / gaps - mean * mean, 0.0)))
        return (f"{self.ticks} ticks, period mean {mean:.3f} ms, std {std:.3f} ms, "
                f"max {self.max_ms:.3f} ms, missed steps {self.missed}")
