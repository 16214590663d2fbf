"""The chapter's experiment: BC vs an offline learner on the same fixed dataset.

Per seed: collect the dataset of the task (``collect_transitions(episodes, expert_frac, seed,
task=...)``; pusher_reach unless ``ExperimentConfig.task`` names another),
train BC and the offline learner, roll both out on the same 100 pooled held-out
episodes (``n_seeds`` suites x ``eval_episodes``, reset seed
``500000 + seed + s * eval_episodes + e``), and score the gap with Newcombe's
interval. Training uses one worker process per core, each (learner, seed) run in
one (``learners/parallel.py``); with one worker all seeds train together in this
process (one ``train_seeds`` call for BC and one for the offline learner). Either way
each seed trains on its own dataset and gets the same numbers.
Each training job writes a resume point (``resume_bc.pt``, ``resume_offline.pt``, in the
seed's directory, or in DIR when all seeds train together) every ``resume_every``
seconds; ``resume=True`` continues a killed experiment from them with the same bytes.
They are removed once the experiment has written its results.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

from ..data.collect import collect_transitions
from ..common.seeds import eval_reset_seeds
from ..common.atomic import write_json_atomic, write_text_atomic
from ..evaluation.rollouts import RolloutResult, format_rate, round6, rollout_task
from ..learners import Progress, TrainConfig
from .loggers import DEFAULT_LOGGER, Logger, check_logger, history_reports, open_logger, progress_scalars
from .parallel import TrainJob, run_jobs
from ..learners.resume import ResumePoints
from ..common.machine import available_cores
from ..serving.checkpoint import save_checkpoint
from ..task.spec import TaskSpec
from ..evaluation.stats import excludes_zero, newcombe_diff_ci, wilson_ci
from ..task.spec import DEFAULT_TASK, load_task


METRIC_KEYS = tuple(sorted((
    "beta", "bc_mean_final_dist", "bc_success_rate", "diff_ci_hi", "diff_ci_lo", "episodes", "expert_frac",
    "gap_significant", "mode", "n_pooled", "naive", "offline_mean_abs_q", "offline_mean_final_dist",
    "offline_success_rate", "seed", "smoke", "steps",
)))


@dataclass
class ExperimentConfig:
    """The experiment's knobs; defaults are the chapter's full run."""

    seeds: list[int] = field(default_factory=lambda: [0])
    algo: str = "awac"  # the offline learner compared against BC ('naive' = Break-It, 'auto' = prior.py's choice)
    expert_frac: float = 0.3
    episodes: int = 200
    steps: int = TrainConfig.steps  # the chapter's hyper-parameters are TrainConfig's defaults
    batch_size: int = TrainConfig.batch_size
    hidden: int = TrainConfig.hidden
    beta: float = TrainConfig.beta
    n_seeds: int = 5  # evaluation suites
    eval_episodes: int = 20  # episodes per suite
    smoke: bool = False
    deterministic: bool = False  # True: fp32 everywhere (see TrainConfig); smoke always
    workers: int | None = None  # training processes; None: one per core (smoke: 1)
    # the offline learner's training time, as steps from its measured rate (prior.py);
    # None: ``steps`` (for 'auto': the chapter's AWAC loop time on this machine)
    budget_s: float | None = None
    task: str = DEFAULT_TASK  # the task collected from and evaluated on (a built-in name or a task file)
    # where the training jobs run: "local" (worker processes of this machine) or "ray"
    # (Ray tasks on the cluster connected by ``ray_engine.connected``); same results
    engine: str = "local"

    @classmethod
    def smoke_settings(cls, **overrides) -> "ExperimentConfig":
        """The chapter's smoke run: small everything, deterministic."""
        base = cls(episodes=20, steps=400, batch_size=64, hidden=64, n_seeds=2, eval_episodes=4, smoke=True)
        return replace(base, **overrides)

    @property
    def naive(self) -> bool:
        return self.algo == "naive"

    @property
    def mode(self) -> str:
        return {"awac": "AWAC", "naive": "naive-maxQ", "auto": "auto"}.get(self.algo, self.algo.upper())

    @property
    def n_pooled(self) -> int:
        return self.n_seeds * self.eval_episodes

    def worker_count(self) -> int:
        if self.workers is not None:
            return max(1, self.workers)
        return 1 if self.smoke else available_cores()

    def train_config(self, algo: str) -> TrainConfig:
        return TrainConfig(
            algo="awac" if algo == "auto" else algo, steps=self.steps, batch_size=self.batch_size, hidden=self.hidden,
            beta=self.beta, deterministic=self.deterministic or self.smoke,
        )

    def offline_config(self, data, log: Callable[[str], None]) -> tuple[TrainConfig, dict | None]:
        """The offline arm's config for one seed's dataset: ``algo``, or for 'auto' the
        learner ``prior`` picks; trained ``steps``, or what ``budget_s`` allows."""
        from .prior import plan_training

        auto = self.algo == "auto"
        # a budget sets the steps; without one, 'auto' takes the chapter's AWAC time, except in
        # the smoke run, which keeps its fixed small steps
        fixed = self.steps if self.budget_s is None and (not auto or self.smoke) else None
        return plan_training(data, self.train_config(self.algo), auto, self.budget_s, fixed, log, load_task(self.task))


def seed_metrics(cfg: ExperimentConfig, seed: int, bc: RolloutResult, offline: RolloutResult, mean_abs_q,
                 offline_steps: int | None = None) -> dict:
    """metrics.json of one seed: exactly the chapter's keys, floats to 6 places.
    ``steps`` is the offline learner's (BC trains ``cfg.steps``; they differ with a budget)."""
    lo, hi = newcombe_diff_ci(offline.successes, offline.episodes, bc.successes, bc.episodes)
    metrics = {
        "mode": cfg.mode,
        "episodes": cfg.episodes,
        "expert_frac": round6(cfg.expert_frac),
        "steps": cfg.steps if offline_steps is None else int(offline_steps),
        "beta": round6(cfg.beta),
        "n_pooled": cfg.n_pooled,
        "bc_success_rate": round6(bc.success_rate),
        "offline_success_rate": round6(offline.success_rate),
        "bc_mean_final_dist": round6(bc.mean_final_dist),
        "offline_mean_final_dist": round6(offline.mean_final_dist),
        "diff_ci_lo": round6(lo),
        "diff_ci_hi": round6(hi),
        "gap_significant": excludes_zero(lo, hi),
        "offline_mean_abs_q": None if mean_abs_q is None else round6(mean_abs_q),
        "naive": cfg.naive,
        "seed": int(seed),
        "smoke": cfg.smoke,
    }
    if tuple(sorted(metrics)) != METRIC_KEYS:
        raise AssertionError(f"metrics keys drifted from the chapter's: {sorted(metrics)}")
    task = load_task(cfg.task)
    if task.name != DEFAULT_TASK:  # pusher_reach's metrics stay the chapter's, byte for byte
        metrics.update(task=task.name, task_digest=task.digest)
    return metrics


@dataclass
class SeedOutcome:
    seed: int
    metrics: dict
    bc: RolloutResult
    offline: RolloutResult
    out_dir: Path


def _progress_printer(label: str, log: Callable[[str], None]) -> Callable[[Progress], None]:
    last = [-1]

    def report(p: Progress) -> None:
        decile = (10 * p.step) // p.total
        if decile == last[0] and p.step != p.total:
            return
        last[0] = decile
        scalars = "  ".join(f"{k} {v:.4g}" for k, v in sorted(p.scalars.items()))
        log(f"  {label:>8} step {p.step:>6}/{p.total}  {p.elapsed_s:6.1f}s  {scalars}")

    return report


def run_experiment(cfg: ExperimentConfig, out_dir: str | Path, log: Callable[[str], None] = print,
                   resume: bool = False, resume_every: float = 1.0, logger: str = DEFAULT_LOGGER) -> list[SeedOutcome]:
    """Run the experiment for every seed of ``cfg``; writes metrics, checkpoints and plots.
    ``resume``: continue the training jobs from the resume points a killed run left.
    ``logger``: where each seed's curves go besides its metrics.json (``loggers``), in the
    seed's directory: ``bc/train/...`` and ``offline/train/...`` while the two arms train,
    ``eval/...`` (both arms' success with Wilson bounds, the gap's interval) at the end."""
    out_dir = Path(out_dir)
    seeds = [int(s) for s in cfg.seeds]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"duplicate seeds in {seeds}")
    check_logger(logger)
    multi = len(seeds) > 1
    seed_dirs = {s: (out_dir / f"seed_{s}" if multi else out_dir) for s in seeds}
    with contextlib.ExitStack() as stack:
        curves = {s: stack.enter_context(open_logger(logger, seed_dirs[s], name=seed_dirs[s].name, resume=resume,
                                                     config=_hparams(cfg, s))) for s in seeds}
        return _run(cfg, out_dir, seeds, seed_dirs, curves, log, resume, resume_every)


def _hparams(cfg: ExperimentConfig, seed: int) -> dict:
    """One seed's settings, for the logger."""
    return {**{k: v for k, v in asdict(cfg).items() if k != "seeds"}, "seed": seed, "mode": cfg.mode}


def _run(cfg: ExperimentConfig, out_dir: Path, seeds: list[int], seed_dirs: dict[int, Path],
         curves: dict[int, Logger], log: Callable[[str], None], resume: bool,
         resume_every: float) -> list[SeedOutcome]:
    from .plots import plot_training_curve

    t0 = time.perf_counter()
    datasets = []
    task = load_task(cfg.task)
    for s in seeds:
        data = collect_transitions(cfg.episodes, cfg.expert_frac, s, task=task)
        datasets.append(data)
        log(f"seed {s}: collected {cfg.episodes} episodes ({len(data)} transitions, expert_frac {cfg.expert_frac})")
    log(f"collection took {time.perf_counter() - t0:.1f}s")

    points: list[ResumePoints] = []

    def resume_points(role: str, job_seeds: list[int]) -> ResumePoints:
        where = seed_dirs[job_seeds[0]] if len(job_seeds) == 1 else out_dir
        # absolute: a Ray task writes it from a worker whose folder may not be this one
        points.append(ResumePoints((where / f"resume_{role}.pt").absolute(), resume_every, resume))
        if resume:
            log(f"resuming from {points[-1].path}" if points[-1].path.exists() else
                f"no resume point at {points[-1].path}; starting")
        return points[-1]

    def curve(role: str, job_seeds: list[int], p: Progress) -> None:
        for m, s in enumerate(job_seeds):  # a job may train several seeds as one ensemble
            curves[s].scalars(p.step, progress_scalars(p, f"{role}/train", member=m))

    plans = [cfg.offline_config(data, log) for data in datasets]
    # the task collected from, recorded in bc.pt and offline.pt
    trained = train_all(cfg, seeds, datasets, log, [p[0] for p in plans], resume_points, task=task, curve=curve)
    outcomes = []
    for m, s in enumerate(seeds):
        reset_seeds = eval_reset_seeds(s, cfg.n_seeds, cfg.eval_episodes)
        bc_res = trained["bc"][m]
        off_res = trained["offline"][m]
        bc_roll = rollout_task(task, bc_res.policy.act, reset_seeds)
        off_roll = rollout_task(task, off_res.policy.act, reset_seeds)
        offline_cfg, plan = plans[m]
        metrics = seed_metrics(cfg, s, bc_roll, off_roll, off_res.mean_abs_q, offline_cfg.steps)
        d = seed_dirs[s]
        d.mkdir(parents=True, exist_ok=True)
        if plan is not None:  # what 'auto' / the budget decided, beside the chapter's metrics
            write_json_atomic(d / "plan.json", {**plan, "algorithm": offline_cfg.algo, "config": offline_cfg.to_dict()})
        save_checkpoint(d / "bc.pt", bc_res.checkpoint)
        save_checkpoint(d / "offline.pt", off_res.checkpoint)
        plot_training_curve(off_res.history, d / "offline_training.png", title=f"{cfg.mode}, seed {s}")
        write_json_atomic(d / "metrics.json", metrics)
        results = seed_scalars(metrics, bc_roll, off_roll)
        curves[s].scalars(metrics["steps"], results)
        curves[s].hparams(_hparams(cfg, s), results)
        outcomes.append(SeedOutcome(s, metrics, bc_roll, off_roll, d))

    if len(seeds) > 1:
        write_summary(cfg, outcomes, out_dir)
    for p in points:
        p.done()  # the results are written: the resume points are spent
    for logger in curves.values():
        logger.drop_previous()
    log(f"total {time.perf_counter() - t0:.1f}s")
    return outcomes


def seed_scalars(metrics: dict, bc: RolloutResult, offline: RolloutResult) -> dict[str, float]:
    """One seed's results as logger tags: metrics.json's numbers, and each arm's Wilson bounds."""
    settings = ("seed", "episodes", "steps", "n_pooled", "beta", "expert_frac")  # the run's settings, not results
    out = {f"eval/{k}": float(v) for k, v in metrics.items()
           if isinstance(v, (int, float)) and not isinstance(v, bool) and k not in settings}
    for arm, result in (("bc", bc), ("offline", offline)):
        lo, hi = wilson_ci(result.successes, result.episodes)
        out[f"eval/{arm}_wilson_ci_lo"], out[f"eval/{arm}_wilson_ci_hi"] = lo, hi
    return out


def train_all(cfg: ExperimentConfig, seeds: list[int], datasets: list, log: Callable[[str], None],
              offline_cfgs: list[TrainConfig] | None = None,
              resume_points: Callable[[str, list[int]], ResumePoints] | None = None,
              task: TaskSpec | None = None,
              curve: Callable[[str, list[int], Progress], None] | None = None) -> dict:
    """{"bc": [TrainResult per seed], "offline": [...]}: BC and the offline learner for
    every seed, one process per core. ``offline_cfgs``: the offline learner's config per
    seed (default: ``cfg.train_config(cfg.algo)``). ``resume_points(role, seeds)``: the
    resume points of the job training ``role`` ("bc" or "offline") for those seeds.
    ``task``: the data's task, recorded in the checkpoints. ``curve(role, seeds, progress)``:
    every progress report of each job, beside the log (on Ray, each run's logged history
    once it is back, without timings)."""
    points = resume_points or (lambda role, job_seeds: None)
    offline_cfgs = offline_cfgs or [cfg.train_config(cfg.algo)] * len(seeds)
    per_seed = {"offline": offline_cfgs, "bc": [cfg.train_config("bc")] * len(seeds)}
    roles = ("offline", "bc")  # the heavier learner first: it starts first
    workers = cfg.worker_count()
    on_ray = cfg.engine == "ray"
    if workers == 1 and not on_ray and all(c == offline_cfgs[0] for c in offline_cfgs):
        jobs = [TrainJob(per_seed[role][0].algo, datasets, per_seed[role][0], seeds, points(role, seeds), task)
                for role in roles]
        job_roles = list(roles)
    else:
        jobs = [TrainJob(f"{per_seed[role][m].algo} s{s}", [datasets[m]], per_seed[role][m], [s], points(role, [s]),
                         task)
                for role in roles for m, s in enumerate(seeds)]
        job_roles = [role for role in roles for _ in seeds]
    role_of = {id(job): role for job, role in zip(jobs, job_roles)}
    workers = min(workers, len(jobs))
    where = "as Ray tasks" if on_ray else "together in this process" if workers == 1 else f"in {workers} worker processes"
    steps = sorted({c.steps for c in offline_cfgs})
    log(f"training {' / '.join(sorted({c.algo for c in offline_cfgs}))} ({' / '.join(map(str, steps))} steps) "
        f"and bc ({cfg.steps} steps), {len(seeds)} seed(s) {where}")
    t1 = time.perf_counter()

    def reporter(job: TrainJob) -> Callable[[Progress], None]:
        printer = _progress_printer(job.label, log)
        if curve is None:
            return printer

        def report(p: Progress) -> None:
            curve(role_of[id(job)], job.seeds, p)
            printer(p)
        return report

    if on_ray:
        from .ray_engine import run_train_jobs

        results = run_train_jobs(jobs, log)
        if curve is not None:  # a Ray task reports no progress: its history, replayed
            for job, job_results in zip(jobs, results):
                for p in history_reports(job_results, job.cfg.steps):
                    curve(role_of[id(job)], job.seeds, p)
    else:
        results = run_jobs(jobs, workers, progress_for=reporter)
    log(f"  training took {time.perf_counter() - t1:.1f}s")
    trained = {}
    per_role = len(jobs) // len(roles)
    for r, role in enumerate(roles):
        trained[role] = [res for job_results in results[r * per_role:(r + 1) * per_role] for res in job_results]
    return trained


def _pooled_row(cfg: ExperimentConfig, outcomes: list[SeedOutcome]) -> dict:
    bc = RolloutResult.concatenate([o.bc for o in outcomes])
    off = RolloutResult.concatenate([o.offline for o in outcomes])
    lo, hi = newcombe_diff_ci(off.successes, off.episodes, bc.successes, bc.episodes)
    return {"label": "pooled", "bc": bc, "offline": off, "diff": (lo, hi), "significant": excludes_zero(lo, hi)}


def summary_rows(cfg: ExperimentConfig, outcomes: list[SeedOutcome]) -> list[dict]:
    """One row per seed plus the row pooled over seeds (all arms' episodes together)."""
    rows = []
    for o in outcomes:
        rows.append({
            "label": f"seed {o.seed}", "bc": o.bc, "offline": o.offline,
            "diff": (o.metrics["diff_ci_lo"], o.metrics["diff_ci_hi"]), "significant": o.metrics["gap_significant"],
        })
    if len(outcomes) > 1:
        rows.append(_pooled_row(cfg, outcomes))
    return rows


def format_table(cfg: ExperimentConfig, rows: list[dict], markdown: bool = False) -> str:
    """BC vs the offline learner with Wilson CIs, the Newcombe difference CI and a verdict."""
    head = ["", "BC success [95% CI]", f"{cfg.mode} success [95% CI]", "BC dist (m)", f"{cfg.mode} dist (m)",
            f"diff {cfg.mode} - BC [95% CI]", "significant"]
    body = []
    for r in rows:
        bc, off = r["bc"], r["offline"]
        lo, hi = r["diff"]
        body.append([
            r["label"], format_rate(bc.successes, bc.episodes), format_rate(off.successes, off.episodes),
            f"{bc.mean_final_dist:.3f}", f"{off.mean_final_dist:.3f}",
            f"{off.success_rate - bc.success_rate:+.3f} [{lo:+.3f}, {hi:+.3f}]", "yes" if r["significant"] else "no",
        ])
    if markdown:
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(row) + " |" for row in body]
        return "\n".join(lines)
    widths = [max(len(str(row[i])) for row in [head] + body) for i in range(len(head))]
    fmt = lambda row: "  ".join(str(c).ljust(w) for c, w in zip(row, widths)).rstrip()  # noqa: E731
    return "\n".join([fmt(head), fmt(["-" * w for w in widths])] + [fmt(row) for row in body])


def verdict(cfg: ExperimentConfig, row: dict) -> str:
    lo, hi = row["diff"]
    if lo > 0:
        return f"{cfg.mode} beats BC: the 95% interval of the difference, [{lo:+.3f}, {hi:+.3f}], excludes 0."
    if hi < 0:
        return f"BC beats {cfg.mode}: the 95% interval of the difference, [{lo:+.3f}, {hi:+.3f}], excludes 0."
    return f"No significant gap: the 95% interval of the difference, [{lo:+.3f}, {hi:+.3f}], contains 0."


def write_summary(cfg: ExperimentConfig, outcomes: list[SeedOutcome], out_dir: Path) -> None:
    """DIR/summary.md (table per seed + pooled) and DIR/summary.png (bars, Wilson errors)."""
    from .plots import plot_success_bars

    rows = summary_rows(cfg, outcomes)
    text = (
        f"# {cfg.mode} vs BC\n\n"
        f"Dataset: {cfg.episodes} episodes, expert_frac {cfg.expert_frac}; {cfg.steps} steps; "
        f"{cfg.n_pooled} pooled held-out episodes per seed ({cfg.n_seeds} suites x {cfg.eval_episodes}).\n"
        f"Success rates with 95% Wilson intervals; the difference with Newcombe's hybrid score interval.\n\n"
        + format_table(cfg, rows, markdown=True) + "\n\n" + verdict(cfg, rows[-1]) + "\n"
    )
    write_text_atomic(out_dir / "summary.md", text)
    bars = []
    for r in rows:
        bc, off = r["bc"], r["offline"]
        bars.append({
            "label": r["label"], "offline_label": cfg.mode,
            "bc_success_rate": bc.success_rate, "bc_ci": wilson_ci(bc.successes, bc.episodes),
            "offline_success_rate": off.success_rate, "offline_ci": wilson_ci(off.successes, off.episodes),
        })
    plot_success_bars(bars, out_dir / "summary.png", title=f"{cfg.mode} vs BC")
