"""The HIL-SERL stage in one process: the reference the ROS stage is measured against.

The arm (the task's env, ``task.envs.make_env``: pusher_reach's ``PusherReachEnv`` by
default), the acting policy (``actor.Actor``, exploring with the learner's latest weights),
the scripted corrector standing in for the person (the task's, ``ScriptedCorrector.for_task``),
and the online learner (``learners/online.py``), stepped in lockstep in one loop: the same
schedule the ROS stage runs across processes (``offline-rl hil --online``), without
DDS. At step n the actor acts on weights version ``n // publish_every`` (trained on
every transition before that version's cut), as the paced policy node does; like the
policy node it answers every state, also those the corrector takes over.

Success without the simulator: with ``success`` naming a success classifier
(``learners.success_classifier``), the learner's reward and the episode's end are the
task's rule with the classifier's judgement of each state in place of the simulator's
(``features.score(..., success_now=...)``); ``end_on_success`` ends an episode where success
is judged (the classifier's, or the simulator's). The simulator's success is still counted
beside it, never trained on: how often the classifier ended an episode the simulator calls
a failure, and missed one it calls a success.

The curve: every ``eval_every`` environment steps the deterministic policy (no
exploration, no corrector) is scored on the held-out reset seeds (the simulator's success at
the episode's end), with the environment steps, robot time, wall time, intervention rate
and critic values so far.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np

from ..common import seeds
from ..serving.actor import Actor
from ..task import features
from ..task.corrector import CorrectorParams, ScriptedCorrector
from ..task.envs import make_env, point_vectors
from ..task.spec import DEFAULT_TASK, load_task
from ..evaluation.rollouts import evaluate_policy
from ..learners.config import TrainConfig
from ..learners.online import OnlineLearner, OnlineSettings
from ..serving.policy import LoadedPolicy
from ..evaluation.stats import wilson_ci
from ..data.transitions import SOURCE_HUMAN, SOURCE_POLICY, Layout, Transitions
from .loggers import Logger, curve_scalars, online_scalars

EVAL_SEED = seeds.HELD_OUT
TRAIN_SEED_BASE = seeds.ONLINE


@dataclass
class OnlineRunConfig:
    env_steps: int = 20_000
    seed: int = 0
    corrections: bool = True  # the scripted corrector takes over (False: online RL alone)
    explore: bool = True  # sample from the policy's Gaussian (False: act deterministically)
    # the corrector also labels every state it leaves to the policy with its expert's action
    # (DAgger's labels): imitated by the actor's BC term, the critic on the executed action
    labels: bool = False
    eval_every: int = 2_500
    eval_episodes: int = 100
    eval_seed: int = EVAL_SEED
    corrector: CorrectorParams = field(default_factory=CorrectorParams)
    settings: OnlineSettings = field(default_factory=OnlineSettings)
    train: TrainConfig = field(default_factory=lambda: TrainConfig(algo="sac"))
    task: str = DEFAULT_TASK  # a built-in task or a task file with a sim section
    success: str | None = None  # a success classifier's file: its judgement, not the simulator's
    end_on_success: bool = False  # an episode ends where success is judged


def transition_row(obs, action, reward, next_obs, info, episode: int, step: int, source: int) -> np.ndarray:
    """One ``/pusher/transition`` row (the task's layout: 25 floats on pusher_reach)."""
    return np.concatenate([obs, action, [reward], next_obs, [info["terminated"], info["truncated"], info["success"],
                                                             episode, step, source]]).astype(np.float32)


def run_online(offline: Transitions, prior: dict | None, cfg: OnlineRunConfig,
               log: Callable[[str], None] = print, logger: Logger | None = None) -> dict:
    """Run the stage for ``cfg.env_steps`` environment steps; returns the summary with its curve.
    ``logger`` (``loggers``) gets, against environment steps, every weights version's
    losses and rates (``online_scalars``) and every curve point (``curve_scalars``)."""
    logger = logger or Logger()
    task = load_task(cfg.task)
    judge = None
    if cfg.success is not None:
        from ..learners.success_classifier import load_classifier

        judge = load_classifier(cfg.success, task)
    learner = OnlineLearner(offline, cfg.train, cfg.settings, cfg.seed, prior)
    actor = Actor(LoadedPolicy(learner.weights()), explore=cfg.explore, seed=cfg.seed,
                  paced_every=cfg.settings.publish_every)
    env = make_env(task, terminate_on_success=False)
    corrector = ScriptedCorrector.for_task(task, CorrectorParams(**{**asdict(cfg.corrector), "seed": cfg.seed}))
    rescored = judge is not None or cfg.end_on_success
    layout = Layout(task.obs_dim, task.act_dim)
    t0 = time.perf_counter()
    curve: list[dict] = []
    counts = {"steps": 0, "human": 0, "takeovers": 0, "episodes": 0, "successes": 0}
    if rescored:  # episodes by who judged them: (judged success, the simulator's success)
        counts.update(judged_successes=0, ended_early=0, false_ends=0, missed=0)
    window = {"steps": 0, "human": 0}

    def evaluate(n: int) -> None:
        ev = evaluate_policy(LoadedPolicy(learner.weights()), cfg.eval_episodes, cfg.eval_seed, task=task)
        lo, hi = wilson_ci(ev["successes"], ev["episodes"])
        point = {"env_steps": n, "robot_s": round(n * task.control_period, 2),
                 "wall_s": round(time.perf_counter() - t0, 2), "updates": learner.updates,
                 "weights_version": learner.version, "success": ev["success_rate"], "successes": ev["successes"],
                 "ci": [round(lo, 4), round(hi, 4)], "final_dist": ev["mean_final_dist"],
                 "intervention_rate": round(window["human"] / max(window["steps"], 1), 4),
                 **{k: round(v, 5) for k, v in learner.losses.items()}}
        curve.append(point)
        logger.scalars(n, curve_scalars(point))
        window.update(steps=0, human=0)
        log(f"  {n:>6} env steps  {point['wall_s']:>7.1f} s  success {ev['successes']}/{ev['episodes']} "
            f"[{lo:.2f}, {hi:.2f}]  final dist {ev['mean_final_dist']:.3f} m  "
            f"interventions {point['intervention_rate']:.3f}")

    evaluate(0)
    episode, n = 0, 0
    while n < cfg.env_steps:
        obs = env.reset(TRAIN_SEED_BASE + 10000 * cfg.seed + episode)
        done, step, was_human, judged = False, 0, False, False
        while not done and n < cfg.env_steps:
            actor.see(n)
            assert actor.ready(), "the learner cut every version due before this step"
            action, source = actor.act(obs, n), SOURCE_POLICY
            label = None
            if cfg.corrections:
                qpos, qvel = env.joint_positions.copy(), env.joint_velocities.copy()
                points = point_vectors(task, env.point_positions())
                correction = corrector.decide(qpos, qvel, env.goal.copy(), points)
                if correction is not None:
                    action, source = correction, SOURCE_HUMAN
                elif cfg.labels:
                    label = corrector.label(qpos, qvel, points)[None]
            next_obs, reward, done, info = env.step(action)
            if rescored:
                truth = info["success"]
                reward, info, judged = rescore(task, env, next_obs, judged, judge, cfg.end_on_success)
                done = info["terminated"] or info["truncated"]
            learner.add(Transitions.from_rows(transition_row(obs, action, reward, next_obs, info, episode, step,
                                                             source)[None], layout), labels=label)
            counts["human"] += source == SOURCE_HUMAN
            counts["takeovers"] += source == SOURCE_HUMAN and not was_human
            window["human"] += source == SOURCE_HUMAN
            window["steps"] += 1
            was_human = source == SOURCE_HUMAN
            obs, step, n = next_obs, step + 1, n + 1
            while learner.updates_owed > 0:
                learner.train()
                if learner.version_due():
                    weights = learner.cut_version()
                    actor.offer(LoadedPolicy(weights))
                    logger.scalars(n, online_scalars(learner, weights, n / (time.perf_counter() - t0)))
            if n % cfg.eval_every == 0:
                evaluate(n)
        counts["episodes"] += 1
        if rescored:
            counts["successes"] += int(truth)
            counts["judged_successes"] += int(judged)
            counts["ended_early"] += int(info["terminated"])
            counts["false_ends"] += int(info["terminated"] and not truth)
            counts["missed"] += int(done and not info["terminated"] and truth and not judged)
        else:
            counts["successes"] += int(info["success"])
        episode += 1
    if n % cfg.eval_every:
        evaluate(n)
    counts["steps"] = n
    if cfg.labels:
        counts["labelled"] = learner.n_labelled
    return {"curve": curve, "counts": counts, "wall_s": round(time.perf_counter() - t0, 2),
            "train_seconds": round(learner.train_seconds, 2), "final_weights": learner.weights(),
            "config": {"env_steps": cfg.env_steps, "seed": cfg.seed, "corrections": cfg.corrections,
                       "explore": cfg.explore, **({"labels": True} if cfg.labels else {}),
                       "corrector": asdict(cfg.corrector), "online": asdict(cfg.settings),
                       "train": cfg.train.to_dict(),
                       **({} if task.name == DEFAULT_TASK else {"task": task.name, "task_digest": task.digest}),
                       **({"success": cfg.success or "simulator", "end_on_success": cfg.end_on_success}
                          if rescored else {})}}


def rescore(task, env, next_obs, success_before: bool, judge, end_on_success: bool) -> tuple[float, dict, bool]:
    """The step just taken, scored by the task's rule with ``judge``'s success (a classifier of
    the next observation; None: the simulator's) and, with ``end_on_success``, ending where it
    is judged a success: (reward, info, judged success)."""
    vectors = {k: v[None] for k, v in env.vectors().items()}
    now = None if judge is None else judge.success(next_obs[None])
    score = features.score(task, env.joint_positions[None], vectors, [env.steps], [success_before], end_on_success,
                           success_now=now)
    success = bool(score.success[0])
    info = {"terminated": bool(score.terminated[0]), "truncated": bool(score.truncated[0]), "success": success,
            "dist": float(score.dist[0])}
    return float(score.reward[0]), info, success


def steps_to(curve: list[dict], threshold: float) -> dict | None:
    """The first curve point at or above ``threshold`` success (env steps and wall time)."""
    for point in curve:
        if point["success"] >= threshold:
            return {"env_steps": point["env_steps"], "wall_s": point["wall_s"]}
    return None
