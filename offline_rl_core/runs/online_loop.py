"""The HIL-SERL stage in one process: the reference the ROS stage is measured against.

The arm (``PusherReachEnv``), the acting policy (``actor.Actor``, exploring with the
learner's latest weights), the scripted corrector standing in for the person, and the
online learner (``learners/online.py``), stepped in lockstep in one loop: the same
schedule the ROS stage runs across processes (``offline-rl hil --online``), without
DDS. At step n the actor acts on weights version ``n // publish_every`` (trained on
every transition before that version's cut), as the paced policy node does; like the
policy node it answers every state, also those the corrector takes over.

The curve: every ``eval_every`` environment steps the deterministic policy (no
exploration, no corrector) is scored on the held-out reset seeds, with the
environment steps, wall time, intervention rate and critic values so far.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np

from ..common import seeds
from ..serving.actor import Actor
from ..task.corrector import CorrectorParams, ScriptedCorrector
from ..task.pusher_reach import PusherReachEnv
from ..evaluation.rollouts import evaluate_policy
from ..learners.config import TrainConfig
from ..learners.online import OnlineLearner, OnlineSettings
from ..serving.policy import LoadedPolicy
from ..evaluation.stats import wilson_ci
from ..data.transitions import SOURCE_HUMAN, SOURCE_POLICY, Transitions
from .loggers import Logger, curve_scalars, online_scalars

EVAL_SEED = seeds.HELD_OUT
TRAIN_SEED_BASE = seeds.ONLINE


@dataclass
class OnlineRunConfig:
    env_steps: int = 20_000
    seed: int = 0
    corrections: bool = True  # the scripted corrector takes over (False: online RL alone)
    explore: bool = True  # sample from the policy's Gaussian (False: act deterministically)
    eval_every: int = 2_500
    eval_episodes: int = 100
    eval_seed: int = EVAL_SEED
    corrector: CorrectorParams = field(default_factory=CorrectorParams)
    settings: OnlineSettings = field(default_factory=OnlineSettings)
    train: TrainConfig = field(default_factory=lambda: TrainConfig(algo="sac"))


def transition_row(obs, action, reward, next_obs, info, episode: int, step: int, source: int) -> np.ndarray:
    """One ``/pusher/transition`` row (the 25-float layout)."""
    return np.concatenate([obs, action, [reward], next_obs, [info["terminated"], info["truncated"], info["success"],
                                                             episode, step, source]]).astype(np.float32)


def run_online(offline: Transitions, prior: dict | None, cfg: OnlineRunConfig,
               log: Callable[[str], None] = print, logger: Logger | None = None) -> dict:
    """Run the stage for ``cfg.env_steps`` environment steps; returns the summary with its curve.
    ``logger`` (``loggers``) gets, against environment steps, every weights version's
    losses and rates (``online_scalars``) and every curve point (``curve_scalars``)."""
    logger = logger or Logger()
    learner = OnlineLearner(offline, cfg.train, cfg.settings, cfg.seed, prior)
    actor = Actor(LoadedPolicy(learner.weights()), explore=cfg.explore, seed=cfg.seed,
                  paced_every=cfg.settings.publish_every)
    env = PusherReachEnv()
    corrector = ScriptedCorrector(CorrectorParams(**{**asdict(cfg.corrector), "seed": cfg.seed}))
    t0 = time.perf_counter()
    curve: list[dict] = []
    counts = {"steps": 0, "human": 0, "takeovers": 0, "episodes": 0, "successes": 0}
    window = {"steps": 0, "human": 0}

    def evaluate(n: int) -> None:
        ev = evaluate_policy(LoadedPolicy(learner.weights()), cfg.eval_episodes, cfg.eval_seed)
        lo, hi = wilson_ci(ev["successes"], ev["episodes"])
        point = {"env_steps": n, "wall_s": round(time.perf_counter() - t0, 2), "updates": learner.updates,
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
        done, step, was_human = False, 0, False
        while not done and n < cfg.env_steps:
            actor.see(n)
            assert actor.ready(), "the learner cut every version due before this step"
            action, source = actor.act(obs, n), SOURCE_POLICY
            correction = corrector.decide(env.qpos.copy(), env.qvel.copy(), env.target[:2]) if cfg.corrections else None
            if correction is not None:
                action, source = correction, SOURCE_HUMAN
            next_obs, reward, done, info = env.step(action)
            learner.add(Transitions.from_rows(transition_row(obs, action, reward, next_obs, info, episode, step,
                                                             source)[None]))
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
        counts["successes"] += int(info["success"])
        episode += 1
    if n % cfg.eval_every:
        evaluate(n)
    counts["steps"] = n
    return {"curve": curve, "counts": counts, "wall_s": round(time.perf_counter() - t0, 2),
            "train_seconds": round(learner.train_seconds, 2), "final_weights": learner.weights(),
            "config": {"env_steps": cfg.env_steps, "seed": cfg.seed, "corrections": cfg.corrections,
                       "explore": cfg.explore, "corrector": asdict(cfg.corrector), "online": asdict(cfg.settings),
                       "train": cfg.train.to_dict()}}


def steps_to(curve: list[dict], threshold: float) -> dict | None:
    """The first curve point at or above ``threshold`` success (env steps and wall time)."""
    for point in curve:
        if point["success"] >= threshold:
            return {"env_steps": point["env_steps"], "wall_s": point["wall_s"]}
    return None
