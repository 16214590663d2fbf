"""The HIL-SERL stage over ROS: ``offline-rl hil --online`` (``make hil-online``).

On a private DDS domain, from ``pusher_bringup``'s ``online.launch.yaml``: the online
learner (``ros2 run learner node``), the policy node acting on its weights (exploring;
paced by the learner in lockstep), the corrections mux, the corrector (scripted stand-in,
a person at the keyboard, or none), a passive recorder writing the whole session, and the
sim. The run ends when the sim has stepped ``env_steps`` times; every process is stopped by
its pid.

The learning curve is scored afterwards from the weights snapshots the learner kept
every ``eval_every`` environment steps (deterministic policy, no corrector, held-out reset
seeds, in the task's own env): success without intervention against environment steps
and against the learner's wall time, with the intervention rate and the critic's values
of each window. Any task with a sim runs, over ROS or ``in_process``.
``DIR/summary.json`` and ``DIR/online.png`` hold them. ``in_process`` runs the same stage
in one process without ROS (``online_loop``): the reference the ROS run is measured
against, and the fast way to run ablations.

``from_topics``: the learner builds its
transitions live from the task's raw topics, as from a robot that publishes only standard
topics; the recorder records those topics (no pusher/transition) until the sim has run
its episodes and the learner has taken every step, and the session's transitions are the
batch join of that recording (``offline-rl dataset``), which are the ones trained on.
"""

from __future__ import annotations

import json
import signal
import sys
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Callable

import numpy as np

from ..common.atomic import write_json_atomic
from ..common.errors import UserError
from ..evaluation.rollouts import evaluate_policy
from ..runs.loggers import DEFAULT_LOGGER, check_logger, curve_scalars, open_logger
from ..runs.online_loop import EVAL_SEED, TRAIN_SEED_BASE, steps_to
from ..serving.checkpoint import load_checkpoint
from ..serving.policy import load_policy
from ..serving.signing import make_session_keys
from ..evaluation.stats import wilson_ci
from ..data.transitions import SOURCE_HUMAN
from ..task.corrector import STEERS, CorrectorParams
from ..task.spec import TaskSpec, load_task

DEFAULT_BAG = "bags/mix.db3"
THRESHOLDS = (0.5, 0.8, 0.9, 0.95)
MAX_LEARNER_RESTARTS = 3
MAX_ACTORS = 16
ACTOR_SEED_STRIDE = 100  # actor i of several explores (and is corrected) with seed 100 * seed + i
REALTIME_THREAD_PRIORITY = 50  # as ros2_control's controller manager
RECORDER_GRACE_S = 20.0  # after the sim's last episode, for the recorder to write it and end


@dataclass
class OnlineHilConfig:
    out: str = "runs/hil-online"
    env_steps: int = 20_000
    seed: int = 0
    prior: str | None = None  # a checkpoint; None: trained as prior_algo says (or reused)
    no_prior: bool = False  # the learner starts from scratch
    # the acting policy serves its mean (tanh of it), not samples of its Gaussian: the arm goes only
    # where the policy or a person's takeover sends it (the corrections are then the exploration)
    no_explore: bool = False
    # the scripted corrector also labels every state it leaves to the policy with its action (DAgger's
    # labels): imitated by the actor's BC term, the critic on the action the arm took
    action_labels: bool = False
    prior_algo: str = "auto"  # auto: the best prior (README, "The best prior"); awac: the chapter's
    prior_steps: int = 8000  # of an AWAC prior
    bags: list[str] = field(default_factory=lambda: [DEFAULT_BAG])
    task: str | None = None  # a built-in task or a task file; None: the one the bags record, else pusher_reach
    corrector: str = "scripted"  # scripted | keyboard | none
    steer: str = "expert"  # how the scripted corrector takes over (task.corrector.STEERS)
    corrector_noise: float = 0.0  # std of Gaussian noise on the scripted corrector's actions (a shaky hand)
    # the scripted corrector's rule (task.corrector.CorrectorParams), in the task's steps: a takeover after
    # ``patience`` steps without progress, handed back after ``hold_steps``; progress judged after the
    # first ``grace_steps`` states of an episode (a task at a lower rate may want fewer)
    patience: int = CorrectorParams.patience
    hold_steps: int = CorrectorParams.hold_steps
    grace_steps: int = CorrectorParams.grace_steps
    mode: str = "lockstep"  # lockstep (paced, reproducible) | realtime (50 Hz)
    utd: int = 2
    offline_ratio: float = 0.5  # share of each batch from the offline bag (OnlineSettings; RLPD's symmetric half)
    imitate_expert: bool = False  # the actor's BC term also on the offline expert rows (OnlineSettings)
    critic_warmup: int = 0  # critic-alone steps on the bag before the first update (OnlineSettings)
    normalize_obs: bool = False  # actor and critic on z-scored observations (TrainConfig, the online learner)
    bc_weight: float = 3.0  # the actor's BC term on a person's actions (TrainConfig; sac)
    lr_decay: bool = False  # learning rates along a cosine to zero over env_steps (OnlineSettings.lr_decay_steps)
    publish_every: int = 50
    eval_every: int = 2500
    eval_episodes: int = 100
    eval_seed: int = EVAL_SEED
    in_process: bool = False
    timeout: float = 4 * 3600.0
    from_topics: bool = False  # the learner joins the task's raw topics instead of pusher/transition
    success: str | None = None  # a success classifier judges success, not the simulator (over ROS: raw topics)
    # an episode ends where success is judged; over ROS (raw topics) the arm's too: the policy
    # node labels it with the classifier (--success), or the sim ends it on its own success
    end_on_success: bool = False
    actors: int = 1  # over ROS: sims (each with its policy node, mux and corrector) feeding the one learner

    @property
    def namespaces(self) -> list[str]:
        """The actors' namespaces: the pipeline's own for one actor, /arm1 ... /armN for several."""
        return [""] if self.actors == 1 else [f"/arm{i}" for i in range(1, self.actors + 1)]

    @property
    def raw_topics(self) -> bool:
        return self.from_topics

    def validate(self) -> None:
        if self.env_steps < 1:
            raise UserError(f"--env-steps must be >= 1 (whole episodes of the task), got {self.env_steps}")
        if not self.in_process:
            if self.action_labels and not self.from_topics:
                raise UserError("--action-labels: over ROS only with --from-topics (the learner joins the labels to "
                                "the raw topics' states by stamp)")
            if self.end_on_success and not self.from_topics:
                raise UserError("--end-on-success: over ROS only with --from-topics (the learner ends the episodes "
                                "it joins from the raw topics where the arm's end)")
            if self.success is not None and not self.from_topics:
                raise UserError("--success: over ROS only with --from-topics (the learner judges the states it "
                                "joins from the raw topics; pusher/transition comes scored by the sim)")
        if self.action_labels and self.corrector != "scripted":
            raise UserError(f"--action-labels: the scripted corrector labels the states (--corrector scripted), "
                            f"not --corrector {self.corrector}")
        if self.success is not None and not Path(self.success).is_file():
            raise UserError(f"--success {self.success}: no such classifier file (train one with "
                            "`offline-rl classifier train`)")
        if self.critic_warmup < 0:
            raise UserError(f"--critic-warmup must be >= 0, got {self.critic_warmup}")
        if not 0.0 <= self.offline_ratio <= 1.0:
            raise UserError(f"--offline-ratio must be in [0, 1], got {self.offline_ratio}")
        for name in ("utd", "publish_every", "eval_every", "eval_episodes"):
            if int(getattr(self, name)) < 1:
                raise UserError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}")
        if self.eval_every % self.publish_every:
            raise UserError(f"--eval-every ({self.eval_every}) must be a multiple of --publish-every "
                            f"({self.publish_every})")
        if self.corrector not in ("scripted", "keyboard", "none"):
            raise UserError(f"--corrector must be scripted, keyboard or none, got {self.corrector!r}")
        if self.steer not in STEERS:
            raise UserError(f"--steer must be one of {', '.join(STEERS)}, got {self.steer!r}")
        if not self.corrector_noise >= 0.0:
            raise UserError(f"--corrector-noise must be >= 0, got {self.corrector_noise}")
        for name in ("patience", "hold_steps"):
            if int(getattr(self, name)) < 1:
                raise UserError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}")
        if int(self.grace_steps) < 0:
            raise UserError(f"--grace-steps must be >= 0, got {self.grace_steps}")
        if self.corrector_noise > 0 and self.corrector != "scripted":
            raise UserError(f"--corrector-noise: the scripted corrector's shaky hand; only with --corrector scripted, "
                            f"got --corrector {self.corrector}")
        if self.steer != "expert" and self.corrector != "scripted":
            raise UserError(f"--steer {self.steer}: how the scripted corrector takes over; only with --corrector "
                            f"scripted, got --corrector {self.corrector}")
        if self.mode not in ("lockstep", "realtime"):
            raise UserError(f"--mode must be lockstep or realtime, got {self.mode!r}")
        if self.corrector == "keyboard" and (self.mode != "realtime" or self.in_process):
            raise UserError("--corrector keyboard needs --mode realtime over ROS (a person acts in real time)")
        if self.corrector == "keyboard" and not sys.stdin.isatty():
            raise UserError("--corrector keyboard needs a terminal on stdin")
        if self.prior_algo not in ("auto", "awac"):
            raise UserError(f"--prior-algo must be auto or awac, got {self.prior_algo!r}")
        if self.prior and self.no_prior:
            raise UserError("--prior and --no-prior contradict each other")
        for bag in self.bags:
            if not Path(bag).exists():
                from .hil import no_such_bag

                raise no_such_bag(bag)
        if self.prior and not Path(self.prior).exists():
            raise UserError(f"{self.prior}: no such checkpoint")
        if self.raw_topics and self.in_process:
            raise UserError("--in-process runs the stage without ROS, on no topics; --from-topics joins "
                            "a robot's topics over ROS")
        if not 1 <= self.actors <= MAX_ACTORS:
            raise UserError(f"--actors must be in [1, {MAX_ACTORS}], got {self.actors}")
        if self.actors > 1:
            given = [flag for flag, value in (("--in-process", self.in_process), ("--from-topics", self.raw_topics),
                                              ("--corrector keyboard", self.corrector == "keyboard")) if value]
            if given:
                raise UserError(f"--actors {self.actors} with {', '.join(given)}: several actors feed the learner "
                                "over ROS on their pusher/transition, each with a scripted corrector or none")

    def check_task(self, task: TaskSpec) -> None:
        """What the run's task must allow: a sim that hosts it (the arm of the session and the
        held-out rollouts of its learning curve), and whole episodes (unless episodes end
        where success is judged)."""
        if not task.sim:
            raise UserError(f"task {task.name} ({task.source_file()}): the online stage runs in a sim and scores "
                            "its learning curve on held-out rollouts there; the task has no sim section")
        steps = task.episodes.max_steps
        early_ends = self.end_on_success or (self.in_process and self.success)
        if not early_ends and (self.env_steps < steps or self.env_steps % steps):
            raise UserError(f"--env-steps must be a positive multiple of {steps} (whole episodes of task "
                            f"{task.name}), got {self.env_steps}")
        if self.actors > 1 and self.env_steps % (steps * self.actors):
            raise UserError(f"--env-steps is the total over the actors: with --actors {self.actors} a multiple of "
                            f"{steps * self.actors} (whole episodes of task {task.name} each), got {self.env_steps}")
        if self.steer == "stick":
            from ..task.envs import task_stick

            task_stick(task)  # UserError naming the task when it is no reach


def run_hil_online(cfg: OnlineHilConfig, log: Callable[[str], None] = lambda s: print(s, file=sys.stderr, flush=True),
                   logger: str = DEFAULT_LOGGER) -> dict:
    """Run the stage; ``logger`` (``runs.loggers``): where the curve goes besides summary.json
    (DIR), and the learner's losses and rates as it trains (DIR/learner, over ROS)."""
    cfg.validate()
    check_logger(logger)
    out = Path(cfg.out)
    from .hil import HilConfig, Loop, hil_session, resolve_prior, resolve_task

    from ..runs.training_run import load_bags, task_of_run

    task = task_of_run(cfg.bags, cfg.task)
    cfg.check_task(task)  # before anything is started or written
    if cfg.success is not None:
        from ..learners.success_classifier import load_classifier

        load_classifier(cfg.success, task)  # another task's classifier: one line, before any node starts
    if not cfg.raw_topics:
        load_bags(cfg.bags, task=task)  # bags of another layout than the task's: one line, before the prior
    loop = Loop(HilConfig(out=str(out), seed=cfg.seed, bags=cfg.bags), log, logger)
    t0 = time.monotonic()
    curves = None  # in process: logged as the stage runs; over ROS: the curve scored after the session
    with hil_session(out, loop):
        task = resolve_task(loop, cfg, out)  # sets cfg.task: the nodes, the join and the rollouts read it
        prior_path, prior_from = (None, "none") if cfg.no_prior else resolve_prior(
            loop, cfg.prior, cfg.bags, cfg.seed, cfg.prior_steps, out, log, cfg.prior_algo)
        if cfg.in_process:
            curves = open_logger(logger, out, name=out.name, config=asdict(cfg))
            try:
                result = _in_process(cfg, task, prior_path, log, curves)
            except BaseException:
                curves.close()
                raise
        else:
            result = _over_ros(cfg, loop, prior_path, out, log, logger)
    summary = _summary(cfg, result, prior_path, prior_from, time.monotonic() - t0)
    with curves or open_logger(logger, out, name=out.name, config=asdict(cfg)) as curves:
        if not cfg.in_process:
            for point in summary["curve"]:
                curves.scalars(point["env_steps"], curve_scalars(point))
        curves.hparams({**asdict(cfg), "prior_from": prior_from},
                       {**curve_scalars(summary["curve"][-1]),
                        "online/intervention_rate_all": summary["intervention_rate"]})
        curves.drop_previous()
    write_json_atomic(out / "summary.json", summary)
    plot_online(summary, out / "online.png")
    final = summary["curve"][-1]
    log(f"hil online: success without intervention {summary['curve'][0]['success']:.2f} -> {final['success']:.2f} "
        f"[{final['ci'][0]:.2f}, {final['ci'][1]:.2f}] after {final['env_steps']} environment steps; "
        + ", ".join(f"{t:g} at {summary['to'][str(t)]['env_steps']} steps" if summary['to'][str(t)] else f"{t:g} not reached"
                    for t in THRESHOLDS)
        + f"; {summary['wall_seconds']:.0f} s; wrote {out / 'summary.json'} and {out / 'online.png'}")
    return summary


def _lr_decay_steps(cfg: OnlineHilConfig) -> int:
    """The learner's ``lr_decay_steps``: the session's budget with ``lr_decay``, else 0 (constant)."""
    return cfg.env_steps if cfg.lr_decay else 0


# ------------------------------------------------------------------------ in one process
def _in_process(cfg: OnlineHilConfig, task, prior_path: Path | None, log, curves) -> dict:
    from ..learners.config import TrainConfig
    from ..learners.online import OnlineSettings
    from ..runs.online_loop import OnlineRunConfig, run_online
    from ..runs.training_run import load_bags

    offline, _ = load_bags(cfg.bags, task=task)
    prior = load_checkpoint(prior_path) if prior_path else None
    run = run_online(offline, prior, OnlineRunConfig(
        env_steps=cfg.env_steps, seed=cfg.seed, corrections=cfg.corrector != "none", explore=not cfg.no_explore,
        labels=cfg.action_labels, eval_every=cfg.eval_every, eval_episodes=cfg.eval_episodes, eval_seed=cfg.eval_seed,
        corrector=CorrectorParams(steer=cfg.steer, noise=cfg.corrector_noise, patience=cfg.patience,
                                  hold_steps=cfg.hold_steps, grace_steps=cfg.grace_steps),
        settings=OnlineSettings(utd=cfg.utd, offline_ratio=cfg.offline_ratio, publish_every=cfg.publish_every,
                                imitate_expert=cfg.imitate_expert,
                                critic_warmup=cfg.critic_warmup, lr_decay_steps=_lr_decay_steps(cfg)),
        train=TrainConfig(algo="sac", normalize_obs=cfg.normalize_obs, bc_weight=cfg.bc_weight),
        task=task, success=cfg.success, end_on_success=cfg.end_on_success),
        log=log, logger=curves)
    return {"curve": run["curve"], "counts": run["counts"], "learner_seconds": run["wall_s"], "where": "in process"}


# ------------------------------------------------------------------------ over ROS
def _over_ros(cfg: OnlineHilConfig, loop, prior_path: Path | None, out: Path, log, logger: str) -> dict:
    learner_dir = out / "learner"
    for stale in (learner_dir / "snapshots").glob("policy_*.pt"):
        stale.unlink()
    (learner_dir / "progress.jsonl").unlink(missing_ok=True)
    # episodes that end early (--end-on-success) leave their count open: the sim runs the
    # session's steps however its episodes end
    episodes = 0 if cfg.end_on_success else cfg.env_steps // load_task(cfg.task).episodes.max_steps
    lockstep = cfg.mode == "lockstep"
    arguments = {
        "bag": cfg.bags[0], "prior": prior_path or "", "out": out, "task": loop.task_arg,
        # until the learner's first weights, the policy serves the prior (or the learner's initial weights)
        "checkpoint": prior_path or learner_dir / "policy.pt",
        "mode": cfg.mode, "paced_every": cfg.publish_every if lockstep else 0, "publish_every": cfg.publish_every,
        "explore": "false" if cfg.no_explore else "true",
        "action_labels": "true" if cfg.action_labels else "false",
        "utd": cfg.utd, "offline_ratio": cfg.offline_ratio,
        "imitate_expert": "true" if cfg.imitate_expert else "false",
        "critic_warmup": cfg.critic_warmup, "normalize_obs": "true" if cfg.normalize_obs else "false",
        "bc_weight": cfg.bc_weight, "lr_decay_steps": _lr_decay_steps(cfg),
        "seed": cfg.seed, "learner_nice": 0 if lockstep else 10,
        # realtime: the nodes that answer the arm go first (where the user may use SCHED_FIFO)
        "thread_priority": 0 if lockstep else REALTIME_THREAD_PRIORITY, "reset_seed": TRAIN_SEED_BASE + 10000 * cfg.seed, "episodes": episodes,
        "snapshot_every": cfg.eval_every, "corrector": cfg.corrector, "steer": cfg.steer,
        "corrector_noise": cfg.corrector_noise, "patience": cfg.patience, "hold_steps": cfg.hold_steps,
        "grace_steps": cfg.grace_steps, "logger": logger,
        "from_topics": "true" if cfg.raw_topics else "false",
        "success": str(Path(cfg.success).resolve()) if cfg.success else "",
        "end_on_success": "true" if cfg.end_on_success else "false",
        # where the episode ends: the classifier's success (the policy node labels it), else the sim's own
        "end_classifier": str(Path(cfg.success).resolve()) if cfg.success and cfg.end_on_success else "",
        "terminate_on_success": "true" if cfg.end_on_success and not cfg.success else "false",
        "steps": cfg.env_steps if cfg.end_on_success else 0,
        "record_topics": _record_topics(cfg) if cfg.raw_topics else "",
        # commands without a header are joined by the sim time of their publication
        "sim_time": "true" if cfg.raw_topics and _joined_by_receive_times(cfg) else "false",
        # a person's corrector runs in the foreground, on this terminal (below)
        "with_corrector": "true" if cfg.corrector == "scripted" else "false",
    }
    if len(cfg.bags) > 1:
        raise UserError("--online takes one offline bag (merge several with offline-rl dataset first)")
    # this session's weights key pair: the policy node takes only weights the learner signed with it
    arguments["keys"] = make_session_keys(out / "keys").signing_key.parent
    over = f" over {cfg.actors} actors ({', '.join(cfg.namespaces)})" if cfg.actors > 1 else ""
    shape = "episodes end at success" if cfg.end_on_success else f"{episodes} episodes"
    log(f"hil online: {cfg.env_steps} environment steps ({shape}{over}, {cfg.mode}) with the "
        f"{cfg.corrector} corrector, learner utd {cfg.utd}, weights every {cfg.publish_every} steps -> {out} "
        f"(ROS_DOMAIN_ID {loop.env['ROS_DOMAIN_ID']})")
    launched = _launch(cfg, loop, arguments, out)
    person = _keyboard_corrector(loop, log) if cfg.corrector == "keyboard" else None
    started = time.monotonic()
    shown, restarts, sim_done = 0, 0, {}
    stopped_recorder = False
    actors = [ns.strip("/") + "/" if ns else "" for ns in cfg.namespaces]  # each actor's label prefix
    log(f"hil online: learner pid {launched['learner'].pid}")
    while launched.finished() is None:
        if time.monotonic() - started > cfg.timeout:
            raise UserError(f"the session did not finish within {cfg.timeout:.0f} s; see {out / 'logs'}")
        if not launched["learner"].running() and restarts < MAX_LEARNER_RESTARTS and cfg.actors == 1:
            restarts += 1
            _restart_learner(cfg, loop, launched, learner_dir, out, restarts, log)
        # every node of the session: one that died (a corrector that could not start) ends it at once
        nodes = [actor + node for actor in actors for node in ("policy", "sim", "mux", "corrector")]
        for name in ["learner"] + [n for n in nodes if n in launched.processes]:
            proc = launched[name]
            if proc.running() or launched.finished() is not None:
                continue
            recorder = launched[name[:-len("sim")] + "recorder"] if name.endswith("sim") else None
            if recorder is not None and proc.poll() == 0 and cfg.raw_topics:
                # the sim ran its episodes: once the learner has every step, the recording ends
                _wait_for_the_learner(cfg, launched, learner_dir, None, log)
                stopped_recorder = launched["recorder"].stop(signal.SIGINT, timeout=60.0) is not None
                break
            if recorder is not None and proc.poll() == 0:
                if not recorder.running():
                    continue  # this actor is done; the others still run
                # the sim ran its episodes: the recorder ends once it has written the last one
                done = sim_done.setdefault(name, time.monotonic())
                if time.monotonic() - done < RECORDER_GRACE_S:
                    continue
                raise UserError(f"the sim ran its {episodes // cfg.actors} episodes but the recorder did not end "
                                f"within {RECORDER_GRACE_S:.0f} s; see {recorder.log_path}")
            raise UserError(f"the {name} node stopped (exit {proc.poll()}); see {proc.log_path}:\n"
                            + "\n".join(proc.output().rstrip().splitlines()[-12:]))
        if person is not None and person.poll() is not None:
            log("hil online: the person quit the keyboard corrector; ending the session")
            break
        progress = _last_progress(learner_dir / "progress.jsonl")
        if progress and progress["trained_through"] >= shown + cfg.env_steps // 20:
            shown = progress["trained_through"]
            log(f"  {shown:>6}/{cfg.env_steps} environment steps  weights v{progress['weights_version']}  "
                f"{progress['updates']} updates  {progress.get('human', 0)} taken over  "
                f"{time.monotonic() - started:6.0f} s  "
                f"critic loss {progress.get('critic_loss', float('nan')):.4f}  "
                f"Q {progress.get('q_policy', float('nan')):+.3f}")
        if stopped_recorder:
            break
        time.sleep(0.5)
    ended = launched.finished()
    rc = 0 if ended is None or stopped_recorder else ended.poll()
    wall = time.monotonic() - started
    bags = [out / ns.strip("/") / "session.db3" for ns in cfg.namespaces]
    if ended is not None and rc == 0 and not cfg.raw_topics:
        _wait_for_the_learner(cfg, launched, learner_dir, bags, log)
    loop.stop_all()  # the learner saves its resume point and final weights on the way out
    if person is not None:
        _stop(person)
    if rc != 0:
        raise UserError(f"the recorder failed (exit {rc}); see {ended.log_path}")
    log(f"hil online: session done in {wall:.0f} s; scoring the learner's snapshots on {cfg.eval_episodes} "
        f"held-out resets each")
    sessions = [session_transitions(cfg, bag) for bag in bags]
    curve = _score_snapshots(cfg, learner_dir, sessions)
    per_actor = {ns: _session_counts(session) for ns, session in zip(cfg.namespaces, sessions)}
    counts = {key: sum(c[key] for c in per_actor.values()) for key in ("steps", "human", "takeovers", "episodes")}
    counts["learner_restarts"] = restarts
    if cfg.action_labels:  # the states the learner joined a label to (live.json: written as it trains)
        try:
            counts["labelled"] = int(json.loads((learner_dir / "live.json").read_text())["labelled"])
        except (OSError, ValueError, KeyError):
            counts["labelled"] = None
    result = {"curve": curve, "counts": counts, "learner_seconds": round(wall, 2), "where": "over ROS"}
    if cfg.actors > 1:
        progress = _last_progress(learner_dir / "progress.jsonl") or {}
        result["actors"] = {ns: {**c, "trained_on": progress.get("received_from", {}).get(ns, 0)}
                            for ns, c in per_actor.items()}
    return result


def _session_counts(session) -> dict:
    human = session.source == SOURCE_HUMAN
    return {"steps": len(session), "human": int(human.sum()),
            "takeovers": int(np.sum(human[1:] & ~human[:-1] & (session.episode[1:] == session.episode[:-1]))),
            "episodes": int(len(np.unique(session.episode)))}


def _launch(cfg: OnlineHilConfig, loop, arguments: dict, out: Path):
    """Start the stage's nodes: one launch of online.launch.yaml for one actor; for several,
    the learner alone (subscribed to every actor's transitions) and then each actor in its
    namespace, its files under OUT/armN, its policy node on the learner's weights."""
    from .processes import LaunchedProcesses

    lockstep = cfg.mode == "lockstep"
    ready = {"learner": "learning from", "policy": "serving", "recorder": "recording"}
    if lockstep:
        ready["mux"] = "mux lockstep"
    if cfg.actors == 1:
        return loop.launch("online.launch.yaml", arguments, out / "logs", ready=ready, timeout=120.0)
    parts = {"": LaunchedProcesses.of("pusher_bringup", "online.launch.yaml", {
        **arguments, "with_actor": "false", "with_corrector": "false", "actors": ", ".join(cfg.namespaces)},
        loop.env, out / "logs")}
    episodes = arguments["episodes"] // cfg.actors
    for i, ns in enumerate(cfg.namespaces):
        parts[ns.strip("/")] = LaunchedProcesses.of("pusher_bringup", "online.launch.yaml", {
            **arguments, "namespace": ns, "out": out / ns.strip("/"), "with_learner": "false",
            "weights_topic": "/learner/weights", "episodes": episodes,
            # the actors share the single actor's training resets, a block each, and explore apart
            "reset_seed": arguments["reset_seed"] + i * episodes, "seed": ACTOR_SEED_STRIDE * cfg.seed + i + 1,
            # state n of an actor waits for the version that holds about n steps of every actor:
            # no actor runs ahead of what the learner has trained on, and the slowest never waits
            "paced_every": -(-cfg.publish_every // cfg.actors) if lockstep else 0,
            # its own pipeline's topics (every topic would be every actor's)
            "record_topics": _actor_record_topics()}, loop.env, out / ns.strip("/") / "logs")
    launched = LaunchedProcesses.together(parts)
    loop.procs.extend(launched.processes.values())  # stopped by stop_all, whatever happens
    return launched.start(ready={f"{part}/{label}" if part else label: text for part in parts
                                 for label, text in ready.items() if (label == "learner") == (part == "")},
                          timeout=120.0)


def _actor_record_topics() -> str:
    """The recorder's --topics for one actor of several: the topics of its namespace's
    pipeline (the sros2 policy's list for a recorder), not the learner's weights."""
    from ..nodes.sros2_policy import NODE_GRAPH

    return "--topics " + " ".join(t for t in NODE_GRAPH["recorder"].subscribe
                                  if not t.startswith("/") and t != "learner/weights")


def session_transitions(cfg: OnlineHilConfig, bag: Path):
    """The session's transitions: those the sim published, or (raw topics) the batch join of
    the recording (judged by the learner's classifier, if it has one), which are the ones the
    learner trained on."""
    if cfg.raw_topics:
        from ..data.raw_topics import transitions_from_topics

        judge = None
        if cfg.success is not None:
            from ..learners.success_classifier import load_classifier

            judge = load_classifier(cfg.success, load_task(cfg.task))
        return transitions_from_topics(bag, cfg.task, judge=judge, end_on_success=cfg.end_on_success)[0]
    from ..data.bag import read_transitions

    return read_transitions(bag)


def _joined_by_receive_times(cfg: OnlineHilConfig) -> bool:
    from ..data.raw_topics import plan_for

    return plan_for(load_task(cfg.task)).receive_stamps


def _record_topics(cfg: OnlineHilConfig) -> str:
    """The recorder's --topics for a raw-topic session: the task's topics (those of a known
    type subscribed from the start: the session's first states are in the bag), its
    description, a person's episode labels and (``action_labels``) the corrector's action labels."""
    from ..data.episode_labels import LABEL_TOPIC
    from ..data.raw_topics import plan_for
    from ..data.task_record import TASK_TOPIC
    from ..task.spec import load_task

    roles = plan_for(load_task(cfg.task), cfg.action_labels).roles
    return (f"--topics {' '.join([*(r.given for r in roles), TASK_TOPIC.lstrip('/'), LABEL_TOPIC])} "
            f"--types {' '.join(f'{r.given}:{r.types[0]}' for r in roles if r.types and len(r.types) == 1)}")


def _wait_for_the_learner(cfg, launched, learner_dir: Path, session_bags: list[Path] | None, log,
                          timeout: float = 300.0) -> None:
    """The session is recorded: let the learner cut the version that holds its last whole
    ``publish_every`` environment steps before it is stopped (a restarted learner can be
    behind), so the final weights are those of a learner that never stopped. Raw topics:
    every step but the session's last (which only a later state could close) is live.
    ``session_bags``: the recordings of the session's actors (None: raw topics)."""
    if session_bags is None:
        recorded = cfg.env_steps - 1
        deadline = time.monotonic() + timeout
        while launched["learner"].running() and time.monotonic() < deadline:
            try:  # the learner has taken (and trained on) every step from the topics
                if json.loads((learner_dir / "live.json").read_text())["steps"] >= recorded:
                    break
            except (OSError, ValueError, KeyError):
                pass
            time.sleep(0.2)
    else:
        from ..data.bag import read_transitions

        recorded = sum(len(read_transitions(bag)) for bag in session_bags)
    last = recorded - recorded % cfg.publish_every
    deadline = time.monotonic() + timeout
    while launched["learner"].running() and time.monotonic() < deadline:
        progress = _last_progress(learner_dir / "progress.jsonl")
        if progress and progress["trained_through"] >= last:
            return
        time.sleep(0.2)
    log(f"hil online: the learner had not trained through the session's {last} transitions when stopped")


def _restart_learner(cfg, loop, launched, learner_dir: Path, out: Path, attempt: int, log) -> None:
    """The learner died: start it again from its last resume point. The session waits for
    it (the paced policy node holds the next state); what arrived while it was down is read
    back from the session bag, once the recorder has flushed it."""
    from ..data.bag import read_transitions
    from .processes import RosProcess

    dead = launched["learner"]
    saved = _last_progress(learner_dir / "progress.jsonl") or {"trained_through": 0}
    log(f"hil online: the learner stopped (exit {dead.poll()}); restarting it from its resume point "
        f"(attempt {attempt} of {MAX_LEARNER_RESTARTS})")
    # in lockstep the sim stops at the state that needs the next version: wait until the
    # recorder has flushed every transition before it (it flushes at least once a second)
    needed = saved["trained_through"] + cfg.publish_every if cfg.mode == "lockstep" else 0
    deadline = time.monotonic() + 30.0
    while needed and time.monotonic() < deadline:
        try:
            if cfg.raw_topics:
                from ..data.raw_topics.build import read_bag
                from ..data.raw_topics.spec import plan_for
                plan = plan_for(load_task(cfg.task))
                if len(read_bag(out / "session.db3", plan)[0].commands) >= needed:
                    break
            elif len(read_transitions(out / "session.db3")) >= needed:
                break
        except UserError:
            pass  # not readable yet
        time.sleep(0.2)
    node = next(n for n in launched.nodes if n.label == "learner")
    node.params["resume"] = True
    proc = RosProcess(node.command(), loop.env, out / "logs" / f"learner.restart{attempt}.log", name="learner")
    loop.procs.append(proc)
    launched.processes["learner"] = proc
    proc.start()
    if not proc.wait_for_output("learning from", 120.0):
        raise UserError(f"the restarted learner did not start; see {proc.log_path}:\n"
                        + "\n".join(proc.output().rstrip().splitlines()[-12:]))
    log(f"hil online: learner pid {proc.pid} resumed")


def _keyboard_corrector(loop, log):
    """A person's corrector, in the foreground on this terminal (its keys, its display);
    stopped by its pid with the rest."""
    import subprocess

    from ros2_shim.ament_index import ros2_run

    log("hil online: you are the corrector: take over with the keys below, space hands back, y / n label the "
        "episode a success / failure (and end it), q quits")
    return subprocess.Popen(ros2_run("corrections", "corrector", "--mode", "keyboard", "--ros-args", "-r",
                                     "__node:=corrector"), env=loop.env)


def _stop(proc) -> None:
    import subprocess

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
        if proc.poll() is not None:
            return
        proc.send_signal(sig)
        try:
            proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            continue


def _last_progress(path: Path) -> dict | None:
    try:
        lines = path.read_text().splitlines()
        return json.loads(lines[-1]) if lines else None
    except (OSError, ValueError):
        return None


def _score_snapshots(cfg: OnlineHilConfig, learner_dir: Path, sessions: list) -> list[dict]:
    """The learning curve: each kept snapshot scored on the held-out resets, with the
    intervention rate of the session's transitions (each actor's recording) before it, and
    last the learner's final weights where they came after the last snapshot (over raw topics
    an episode's last step makes no transition: 200 episodes of 100 steps train on 19,800, and
    a snapshot every 2,500 would leave the last 2,300 unscored)."""
    humans = [session.source == SOURCE_HUMAN for session in sessions]
    progress = {}
    for line in (learner_dir / "progress.jsonl").read_text().splitlines():
        row = json.loads(line)
        progress[row["trained_through"]] = row
    curve = []
    snapshots = sorted((learner_dir / "snapshots").glob("policy_*.pt"))
    if not snapshots:
        raise UserError(f"{learner_dir / 'snapshots'}: the learner kept no snapshots")
    kept = [(path, load_checkpoint(path)) for path in snapshots]
    final = learner_dir / "policy.pt"
    if final.exists():
        last = load_checkpoint(final)
        if int(last.get("trained_through", 0)) > int(kept[-1][1].get("trained_through", 0)):
            kept.append((final, last))
    previous = 0
    for path, ckpt in kept:
        n = int(ckpt.get("trained_through", 0))
        task = load_task(cfg.task)
        ev = evaluate_policy(load_policy(path, task), cfg.eval_episodes, cfg.eval_seed, task=task)
        lo, hi = wilson_ci(ev["successes"], ev["episodes"])
        # paced, the actors keep in step: each had taken about its share of the learner's steps
        window = np.concatenate([human[previous // len(humans):n // len(humans)] for human in humans])
        p = progress.get(n, {})
        curve.append({"env_steps": n, "wall_s": float(ckpt.get("wall_s", 0.0)), "updates": int(ckpt.get("updates", 0)),
                      "weights_version": int(ckpt.get("weights_version", 0)), "success": ev["success_rate"],
                      "successes": ev["successes"], "ci": [round(lo, 4), round(hi, 4)],
                      "final_dist": ev["mean_final_dist"],
                      "intervention_rate": round(float(window.mean()), 4) if len(window) else 0.0,
                      **{k: p[k] for k in ("critic_loss", "policy_loss", "q_policy", "log_std") if k in p}})
        previous = n
    return curve


# ------------------------------------------------------------------------ results
def rescore(run_dir: Path) -> dict:
    """Score an over-ROS session's kept weights again (its snapshots and final weights) as the
    stage scores them, and rewrite its ``summary.json`` with that curve: for a session scored
    before its final weights were (``_score_snapshots``). Counts and wall times stay as run."""
    run_dir = Path(run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    if summary.get("where") != "over ROS":
        raise UserError(f"{run_dir / 'summary.json'}: not a session over ROS (only its kept weights can be scored again)")
    known = {f.name for f in fields(OnlineHilConfig)}
    cfg = OnlineHilConfig(**{**{k: v for k, v in summary["config"].items() if k in known}, "out": str(run_dir)})
    sessions = [session_transitions(cfg, run_dir / ns.strip("/") / "session.db3") for ns in cfg.namespaces]
    summary.update(_curve_summary(_score_snapshots(cfg, run_dir / "learner", sessions)))
    write_json_atomic(run_dir / "summary.json", summary)
    return summary


def _curve_summary(curve: list[dict]) -> dict:
    """What a summary says of its learning curve: the curve, the steps to each threshold, the end."""
    final = curve[-1]
    return {"curve": curve, "to": {str(t): steps_to(curve, t) for t in THRESHOLDS},
            "final_success": final["success"], "final_ci": final["ci"], "final_dist": final["final_dist"]}


def _summary(cfg: OnlineHilConfig, result: dict, prior_path, prior_from: str, wall: float) -> dict:
    curve = result["curve"]
    return {
        "where": result["where"],
        **_curve_summary(curve),
        "prior_success": curve[0]["success"],
        "counts": result["counts"],
        "intervention_rate": round(result["counts"]["human"] / max(result["counts"]["steps"], 1), 4),
        **({"actors": result["actors"]} if "actors" in result else {}),  # several actors: each one's counts
        "prior": None if prior_path is None else str(prior_path),
        "prior_from": prior_from,
        "config": asdict(cfg),
        "learner_wall_seconds": result["learner_seconds"],
        "wall_seconds": round(wall, 1),
    }


def plot_online(summary: dict, path: Path) -> None:
    from ..runs.plots import _save_atomic, plt

    curve = summary["curve"]
    steps = [p["env_steps"] for p in curve]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    ax = axes[0]
    ax.plot(steps, [p["success"] for p in curve], "o-", label="success without intervention")
    ax.fill_between(steps, [p["ci"][0] for p in curve], [p["ci"][1] for p in curve], alpha=0.2)
    ax.plot(steps, [p["intervention_rate"] for p in curve], "s--", label="intervention rate (window)")
    ax.set_xlabel("environment steps")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    ax = axes[1]
    ax.plot([p["wall_s"] for p in curve], [p["success"] for p in curve], "o-")
    ax.set_xlabel("learner wall time (s)")
    ax.set_ylabel("success without intervention")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax = axes[2]
    if any("q_policy" in p for p in curve):
        ax.plot(steps, [p.get("q_policy", np.nan) for p in curve], "o-", label="mean Q(s, pi(s)) of a batch")
        ax.plot(steps, [p.get("critic_loss", np.nan) for p in curve], "s--", label="critic loss")
        ax.legend(fontsize=8)
    ax.set_xlabel("environment steps")
    ax.grid(alpha=0.3)
    fig.suptitle(f"HIL-SERL online stage ({summary['where']}, seed {summary['config']['seed']}, "
                 f"corrector {summary['config']['corrector']}, prior {summary['prior_from']})")
    _save_atomic(fig, path)
