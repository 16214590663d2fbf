"""The one training loop: sample, update, log every k steps, package checkpoints.

``train_seeds`` trains one run per seed, all together as one ensemble: the networks
of all runs are stacked, so each step is a few batched matmuls instead of a few per
run. Each run keeps its own init, its own batch stream and its own dataset, so its
result does not depend on which runs train beside it.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from ..common.errors import UserError
from ..serving.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, task_field
from ..serving.policy import LoadedPolicy
from ..data.transitions import Transitions
from .awac import AWAC
from .bc import BC
from .config import TrainConfig
from .data import IndexSampler, MemberData, correction_pools, goal_episode_rows, top_episode_rows
from .filtered_bc import FilteredBC
from .iql import IQL
from .naive import NaiveMaxQ
from .sac import SAC
from .resume import ResumePoints, learner_training_state, load_learner_training_state
from .normalize import fold, normalized, obs_stats, unfold
from .schedule import LearningRates
from .stepper import intra_op_threads, make_step

LEARNERS = {"bc": BC, "filtered_bc": FilteredBC, "awac": AWAC, "iql": IQL, "naive": NaiveMaxQ, "sac": SAC}


@dataclass
class Progress:
    step: int
    total: int
    elapsed_s: float
    scalars: dict[str, float]  # each loss, the mean over the runs trained together
    member_scalars: dict[str, list[float]] | None = None  # each loss of each run, in seed order


@dataclass
class TrainResult:
    seed: int
    policy: LoadedPolicy
    checkpoint: dict
    history: dict[str, list[float]] = field(default_factory=dict)
    mean_abs_q: float | None = None
    step_kind: str = "eager"  # how the steps ran: "cpp" / "python" replay of the recorded update, or "eager"


@contextlib.contextmanager
def torch_threads(n: int):
    previous = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def on_device(device: str):
    """Make ``device`` current while training (CUDA streams and graphs use the current device)."""
    dev = torch.device(device)
    return torch.cuda.device(dev) if dev.type == "cuda" else contextlib.nullcontext()


def seed_generators(seed: int) -> tuple[torch.Generator, torch.Generator]:
    """(init generator, batch-index generator) for one run, from independent streams."""
    init_seed, sample_seed = np.random.SeedSequence(seed).generate_state(2, dtype=np.uint64)
    return (torch.Generator().manual_seed(int(init_seed)), torch.Generator().manual_seed(int(sample_seed)))


def _member_pools(data: Transitions, cfg: TrainConfig, task=None):
    if cfg.algo == "filtered_bc":
        rows = goal_episode_rows(data, task) if cfg.filter_by == "goal" else top_episode_rows(data, cfg.filter_top_frac)
        return (torch.from_numpy(rows), None)
    if cfg.correction_ratio is not None:
        prior, corrections = correction_pools(data)
        if len(corrections) and len(prior):
            return (torch.from_numpy(prior), torch.from_numpy(corrections))
    return None


THREADS_CHECK_EVERY = 100  # steps between asking ``threads_now`` (a few microseconds each)


def train_seeds(
    datasets: Transitions | list[Transitions],
    cfg: TrainConfig,
    seeds: list[int],
    progress: Callable[[Progress], None] | None = None,
    init: dict | None = None,
    resume: ResumePoints | None = None,
    snapshot: Callable[[int, float, Callable[[int], dict]], None] | None = None,
    threads_now: Callable[[], int] | None = None,
    task=None,
) -> list[TrainResult]:
    """Train ``cfg.algo`` once per seed; ``datasets`` is one Transitions for all seeds
    or one per seed. ``init`` (a checkpoint dict) warm-starts every run from it.
    ``resume``: write a resume point every ``resume.every_s`` seconds, and with
    ``resume.resume`` start from the one there (the result is the same bytes as a run
    that was never stopped). ``snapshot(step, elapsed_s, policy_state)`` is called at every
    log point (every ``cfg.log_every`` steps and the last), e.g. to keep the policies of
    a learning curve: ``policy_state(m)`` is member m's policy as a checkpoint holds it.
    ``threads_now()``: the threads the steps may use from now on (asked every
    ``THREADS_CHECK_EVERY`` steps unless ``cfg.threads`` fixes them), e.g. more once the
    runs beside this one have finished; the result is the same bytes either way.
    ``task`` (a ``TaskSpec``): the task the data is of, recorded in every checkpoint
    (``checkpoint["task"]``), which also says where an episode ends at the goal (filtered BC by
    goal; default pusher_reach's columns); the data's sizes must be its observation and action sizes."""
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("no seeds to train")
    if isinstance(datasets, Transitions):
        datasets = [datasets] * len(seeds)
    if len(datasets) != len(seeds):
        raise ValueError(f"{len(datasets)} datasets for {len(seeds)} seeds")
    for d in datasets:
        if len(d) == 0:
            raise ValueError("cannot train on an empty dataset")
    obs_dim, act_dim = datasets[0].obs.shape[1], datasets[0].action.shape[1]
    if task is not None and (obs_dim, act_dim) != (task.obs_dim, task.act_dim):
        raise ValueError(f"the data has obs {obs_dim}, action {act_dim}; task {task.name} has obs {task.obs_dim}, "
                         f"action {task.act_dim}")

    gens = [seed_generators(s) for s in seeds]
    learner = LEARNERS[cfg.algo](cfg, len(seeds), [g[0] for g in gens], obs_dim, act_dim)
    pools = [_member_pools(d, cfg, task) for d in datasets]
    # --normalize-obs: train on z-scored observations (stats of the rows each member samples),
    # save networks with the stats folded in; identity otherwise
    norms = [obs_stats(d, None if p is None else p[0].numpy()) for d, p in zip(datasets, pools)] \
        if cfg.normalize_obs else None
    to_raw = (lambda m, state: fold(state, *norms[m])) if norms else (lambda m, state: state)
    if init is not None:
        for m in range(len(seeds)):
            policy_state, learner_state = init["policy_state"], init.get("learner_state") or {}
            if norms:  # the warm start's networks take raw observations: unfold them
                policy_state, learner_state = unfold(policy_state, *norms[m]), unfold(learner_state, *norms[m])
            learner.policy.load_member_state(m, policy_state)
            learner.load_learner_state(m, learner_state)
    if norms:
        copies: dict = {}  # members sharing a dataset (and so its stats) share its copy
        train_sets = [copies.setdefault(id(d), normalized(d, *n)) for d, n in zip(datasets, norms)]
    else:
        train_sets = datasets
    data = MemberData(train_sets, cfg.device)
    sampler = IndexSampler(data.sizes, cfg.batch_size, [g[1] for g in gens],
                           pools if any(p is not None for p in pools) else None, cfg.correction_ratio, cfg.device)
    step_once = make_step(learner.update, data, (len(seeds), cfg.batch_size), cfg.device, cfg.cuda_graph, cfg.threads)

    histories: list[dict[str, list[float]]] = [{"step": []} for _ in seeds]
    first_step, before = 1, 0.0
    identity = {"config": cfg.to_dict(), "seeds": seeds, "datasets": [d.content_hash() for d in datasets],
                "init": None if init is None else init.get("dataset_hash")} if resume is not None else None
    saved = resume.read() if resume is not None else None
    if saved is not None:
        if saved["identity"] != identity:
            raise UserError(f"{resume.path}: that resume point is of another run (settings, seeds or data differ)")
        try:
            load_learner_training_state(learner, saved["learner"])
        except KeyError as exc:
            raise UserError(f"{resume.path}: that resume point lacks {exc} (written by another version of "
                            "pusher-rl); delete it to start over") from None
        sampler.load_state(saved["sampler"])
        histories, first_step, before = saved["histories"], int(saved["step"]) + 1, float(saved["elapsed_s"])
    rates = LearningRates(learner, cfg.lr_schedule, cfg.steps)  # after a resume point's optimiser state
    start = time.perf_counter() - before
    with torch_threads(intra_op_threads(cfg.threads)), on_device(cfg.device):
        for step in range(first_step, cfg.steps + 1):
            rates.at(step)
            if threads_now is not None and cfg.threads is None and step % THREADS_CHECK_EVERY == 0 \
                    and hasattr(step_once, "offer_threads"):
                step_once.offer_threads(threads_now())
            losses = step_once(sampler.next())
            if step % cfg.log_every == 0 or step == cfg.steps:
                values = {k: v.float().tolist() for k, v in losses.items()}  # the only host sync
                for m, hist in enumerate(histories):
                    hist["step"].append(step)
                    for k, v in values.items():
                        hist.setdefault(k, []).append(v[m])
                if progress is not None:
                    scalars = {k: float(np.mean(v)) for k, v in values.items()}
                    progress(Progress(step, cfg.steps, time.perf_counter() - start, scalars, values))
                if snapshot is not None:
                    snapshot(step, time.perf_counter() - start, lambda m: to_raw(m, learner.policy.member_state(m)))
            if resume is not None and step < cfg.steps and resume.due():
                resume.write({"identity": identity, "step": step, "histories": histories,
                              "elapsed_s": time.perf_counter() - start, "sampler": sampler.state(),
                              "learner": learner_training_state(learner)})
        mean_abs_q = learner.mean_abs_q(data)
    step_kind = getattr(step_once, "kind", "eager")

    hashes: dict[int, str] = {}
    results = []
    for m, seed in enumerate(seeds):
        key = id(datasets[m])
        if key not in hashes:
            hashes[key] = datasets[m].content_hash()
        checkpoint = {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "algorithm": cfg.algo,
            "obs_dim": obs_dim,
            "act_dim": act_dim,
            "hidden": cfg.hidden,
            "policy_state": to_raw(m, learner.policy.member_state(m)),
            "obs_mean": None,
            "obs_std": None,
            "learner_state": to_raw(m, learner.learner_state(m)),
            "config": cfg.to_dict(),
            "seed": seed,
            "dataset_hash": hashes[key],
            "transitions": len(datasets[m]),
            "mean_abs_q": None if mean_abs_q is None else float(mean_abs_q[m]),
            "train_seconds": round(time.perf_counter() - start, 3),
            "train_step": step_kind,
            "train_threads": getattr(step_once, "threads", None),
            "kernels": learner.policy.kernels if cfg.device == "cpu" else cfg.device,
        }
        if task is not None:
            checkpoint["task"] = task_field(task)
        results.append(TrainResult(seed, LoadedPolicy(checkpoint), checkpoint, histories[m],
                                   None if mean_abs_q is None else float(mean_abs_q[m]), step_kind))
    return results


def train(dataset: Transitions, cfg: TrainConfig, seed: int, progress=None, init=None,
          resume: ResumePoints | None = None, snapshot=None, task=None) -> TrainResult:
    """One run: ``train_seeds`` with a single seed."""
    return train_seeds(dataset, cfg, [seed], progress, init, resume, snapshot, task=task)[0]
