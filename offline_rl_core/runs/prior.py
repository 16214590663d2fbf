"""``--algo auto`` and ``--budget-s``: the learner, and how long to train it, from what
the bag holds and the time the user gives.

What the bag holds (``profile_bag``): its episodes and their returns, and how many of
them are *expert-like*: they end at the goal (the last observation within the success
tolerance of the target, ``learners.data.episodes_at_goal``). A scripted or skilled
demonstration ends there; random actions almost never do (1 or 2 episodes in 140 here),
even those that pass through the goal on the way. Ranking episodes by return instead lets
in random episodes that merely started near the target (8 of the "top 30 %" of the
chapter's mix). The recipe (``choose_recipe``), chosen on validation data only
(bench/RESULTS.md, "Choosing the prior"):

- at least ``MIN_EXPERT_EPISODES`` expert-like episodes: filtered BC on exactly those,
  on z-scored observations (``--normalize-obs``); when every episode is expert-like
  that is plain BC;
- fewer: AWAC with the chapter's settings, which can still learn from poor data.

The time (``plan_training``) becomes a step count before training starts, from the
learner's step rate on this machine (``step_rate``: measured once, then cached like the
kernel choice), so a run is reproducible: the steps are recorded in metrics.json, and the
same seed and steps give the same bytes. The default budget is the wall time of the
chapter's own AWAC loop (8000 steps, ``runs/chapter_loop.py``) on this
machine, measured the same way.
"""

from __future__ import annotations

import math
import os
import statistics
import time
from dataclasses import asdict, dataclass, replace
from typing import Callable

import numpy as np
import torch

from ..common.errors import UserError
from ..common.machine import available_cores, machine_key, read_cache, write_cache
from ..learners import TrainConfig, train
from ..learners.data import episodes_at_goal
from ..learners.stepper import step_threads
from ..data.transitions import Transitions

# Fewer expert-like episodes than this and cloning them is not trusted: with 7 or 8 (2.5 %
# expert data) cloning still beat AWAC given the same time; fewer was not measured.
MIN_EXPERT_EPISODES = 5
# Share of the budget spent in gradient steps; the rest absorbs step-rate noise and the
# run's set-up (recording the step, evaluation, writing files).
TRAIN_SHARE = 0.85
CHAPTER_STEPS = 8000  # the chapter's AWAC run
# Cloning converged on validation data within 350 passes over the cloned rows (success
# 0.99-1.00 from there to 4000 passes): auto stops at this many, budget or not.
CLONE_PASSES = 1000
CACHE_FILE = "step_rates.json"
DEFAULT_BUDGET_FROM = "the chapter's 8000-step AWAC loop on this machine (measured, cached)"  # plan["budget_from"]


@dataclass(frozen=True)
class BagProfile:
    episodes: int
    transitions: int
    expert_like: int  # episodes that end at the goal
    expert_like_transitions: int
    mean_return: float
    expert_like_mean_return: float | None
    other_mean_return: float | None

    @property
    def expert_like_share(self) -> float:
        return self.expert_like / self.episodes if self.episodes else 0.0

    def as_dict(self) -> dict:
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in asdict(self).items()} | \
            {"expert_like_share": round(self.expert_like_share, 6)}


def profile_bag(data: Transitions, task=None) -> BagProfile:
    """``task`` (default pusher_reach): where its episodes end at the goal (``episodes_at_goal``)."""
    if len(data) == 0:
        raise UserError("the bag holds no transitions to train on")
    _, returns, _ = data.episode_returns()  # sorted by episode id, as episodes_at_goal
    ids, at_goal = episodes_at_goal(data, task)
    mean = lambda a: float(a.mean()) if len(a) else None  # noqa: E731
    rows = int(np.isin(data.episode, ids[at_goal]).sum())
    return BagProfile(len(returns), len(data), int(at_goal.sum()), rows, float(returns.mean()),
                      mean(returns[at_goal]), mean(returns[~at_goal]))


@dataclass(frozen=True)
class Recipe:
    algo: str
    overrides: dict  # TrainConfig fields besides algo and steps
    reason: str
    rows: int | None = None  # rows it clones: it needs at most CLONE_PASSES passes over them

    def max_steps(self, batch_size: int, quantum: int = 100) -> int | None:
        if self.rows is None:
            return None
        return max(quantum, math.ceil(CLONE_PASSES * self.rows / batch_size / quantum) * quantum)


def choose_recipe(profile: BagProfile) -> Recipe:
    k, n = profile.expert_like, profile.episodes
    if k >= MIN_EXPERT_EPISODES and k == n:
        return Recipe("bc", {"normalize_obs": True},
                      f"{k} of {n} episodes end at the goal: clone them all (BC on z-scored observations)",
                      profile.transitions)
    if k >= MIN_EXPERT_EPISODES:
        return Recipe("filtered_bc", {"filter_by": "goal", "normalize_obs": True},
                      f"{k} of {n} episodes end at the goal: clone those (filtered BC on z-scored observations)",
                      profile.expert_like_transitions)
    return Recipe("awac", {},
                  f"only {k} of {n} episodes end at the goal (fewer than {MIN_EXPERT_EPISODES}): "
                  f"AWAC, which learns from poor data too")


# ---- time -> steps ---------------------------------------------------------------------

def _step_kind(cfg: TrainConfig) -> tuple:
    """What a step's cost depends on (filtered BC steps cost what BC's do)."""
    algo = "bc" if cfg.algo == "filtered_bc" else cfg.algo
    return (algo, cfg.batch_size, cfg.hidden, step_threads(cfg.threads), cfg.deterministic, cfg.device,
            cfg.correction_ratio is not None)


def _time_ours(cfg: TrainConfig, data: Transitions, steps: int, warm: int, task=None) -> float:
    """Seconds per step of ``cfg``'s learner on ``data`` after ``warm`` steps (set-up and recording);
    ``task``: the data's, which says where its episodes end at the goal (filtered BC by goal)."""
    marks = {}
    run = replace(cfg, steps=warm + steps, log_every=warm)  # steps: a multiple of warm
    train(data, run, seed=0, snapshot=lambda step, elapsed, _: marks.__setitem__(step, elapsed), task=task)
    return (marks[warm + steps] - marks[warm]) / steps


def _time_chapter(data: Transitions, steps: int, threads: int) -> float:
    """Seconds per step of the chapter's AWAC loop (the difference of a long and a short run
    removes its set-up)."""
    from . import chapter_loop as chapter

    tensors = chapter.dataset_tensors(data)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        times = []
        for n in (10, 10 + steps):
            torch.manual_seed(0)
            t0 = time.perf_counter()
            chapter.train_awac(tensors, chapter.ChapterSettings(steps=n))
            times.append(time.perf_counter() - t0)
    finally:
        torch.set_num_threads(before)
    return (times[1] - times[0]) / steps


def _load_note(log: Callable[[str], None]) -> dict:
    """The machine's load as a measurement starts (kept beside it), and a warning when other
    work competes for the cores: a rate measured then is low for good, and every budget in
    seconds (equal wall time) follows it."""
    load = round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else 0.0
    cores = available_cores()
    if load > cores:
        log(f"warning: the machine is busy (load {load:.1f} on {cores} cores): what is measured now is cached "
            f"({CACHE_FILE} in ~/.cache/pusher-rl) and every budget in seconds follows it; delete the file to measure "
            "again when the machine is idle")
    return {"load": load, "cores": cores}


def step_rate(cfg: TrainConfig, data: Transitions, log: Callable[[str], None] = lambda s: None,
              task=None) -> float:
    """Steps per second of ``cfg``'s learner on this machine (measured once, then cached), timed
    on ``data`` of ``task`` (a ``TaskSpec``; default pusher_reach)."""
    key = machine_key("ours", *_step_kind(cfg))
    cache = read_cache(CACHE_FILE)
    if key not in cache:
        log("measuring this learner's step rate on this machine (once; cached in ~/.cache/pusher-rl)")
        load = _load_note(log)
        bc_like = cfg.algo in ("bc", "filtered_bc")
        samples = [_time_ours(cfg, data, 400 if bc_like else 100, 20, task) for _ in range(3)]
        write_cache(key, {"steps_per_s": round(1.0 / statistics.median(samples), 3), "what": list(map(str, _step_kind(cfg))),
                          "measured": time.strftime("%Y-%m-%dT%H:%M:%S"), **load}, CACHE_FILE)
        cache = read_cache(CACHE_FILE)
        if key not in cache:  # an unwritable cache: use the measurement as it is
            return round(1.0 / statistics.median(samples), 3)
    return float(cache[key]["steps_per_s"])


def chapter_awac_seconds(data: Transitions, log: Callable[[str], None] = lambda s: None) -> float:
    """Wall time of the chapter's 8000-step AWAC loop on this machine: the faster of one
    torch thread and torch's default, extrapolated from 300-step runs (measured once, cached)."""
    threads = sorted({1, torch.get_num_threads()})
    key = machine_key("chapter_awac", CHAPTER_STEPS, *threads)
    cache = read_cache(CACHE_FILE)
    if key not in cache:
        log("timing the chapter's AWAC loop on this machine for the default budget (once; about 30 s)")
        load = _load_note(log)
        per_step = min(statistics.median(_time_chapter(data, 300, t) for _ in range(3)) for t in threads)
        seconds = round(per_step * CHAPTER_STEPS, 3)
        write_cache(key, {"seconds": seconds, "threads": threads, "measured": time.strftime("%Y-%m-%dT%H:%M:%S"), **load},
                    CACHE_FILE)
        return float(read_cache(CACHE_FILE).get(key, {"seconds": seconds})["seconds"])
    return float(cache[key]["seconds"])


def steps_for_budget(budget_s: float, steps_per_s: float, quantum: int = 100) -> int:
    """Gradient steps that fit ``TRAIN_SHARE`` of ``budget_s``, in whole ``quantum``s."""
    steps = int(math.floor(budget_s * TRAIN_SHARE * steps_per_s / quantum)) * quantum
    return max(quantum, steps)


def plan_training(data: Transitions, cfg: TrainConfig, auto: bool, budget_s: float | None, steps: int | None,
                  log: Callable[[str], None] = lambda s: None, task=None) -> tuple[TrainConfig, dict | None]:
    """The config to train and, for ``auto`` or a budget, what was decided and why (for
    metrics.json). ``steps`` given wins; otherwise a budget (given, or for ``auto`` the
    chapter's AWAC time) becomes steps; otherwise ``cfg.steps`` stands. ``task``: the data's
    (default pusher_reach)."""
    if steps is not None and budget_s is not None:
        raise UserError("give --steps or --budget-s, not both")
    if budget_s is not None and not budget_s > 0:
        raise UserError(f"--budget-s must be > 0 seconds, got {budget_s}")
    if steps is not None:
        cfg = replace(cfg, steps=int(steps))
    if not auto and budget_s is None:
        return cfg, None
    info: dict = {}
    recipe = None
    if auto:
        profile = profile_bag(data, task)
        recipe = choose_recipe(profile)
        cfg = replace(cfg, algo=recipe.algo, **recipe.overrides)
        info.update(profile=profile.as_dict(), choice=recipe.algo, reason=recipe.reason)
        log(f"auto: {recipe.reason}")
    if steps is None:
        budget_from = "--budget-s"
        if budget_s is None:
            budget_s = chapter_awac_seconds(data, log)
            budget_from = DEFAULT_BUDGET_FROM
        rate = step_rate(cfg, data, log, task)
        budget_steps = steps_for_budget(budget_s, rate)
        cap = recipe.max_steps(cfg.batch_size) if recipe is not None else None
        cfg = replace(cfg, steps=budget_steps if cap is None else min(cap, budget_steps))
        info.update(budget_s=round(float(budget_s), 3), budget_from=budget_from, steps_per_s=rate,
                    budget_steps=budget_steps, max_steps=cap)
        log(f"budget {budget_s:.1f} s ({budget_from}): {budget_steps} steps at {rate:.0f} steps/s"
            + (f"; the data needs at most {cap} ({CLONE_PASSES} passes over its {recipe.rows} cloned rows)"
               if cap is not None else "") + f": {cfg.steps} steps")
    info["steps"] = cfg.steps
    return cfg, info
