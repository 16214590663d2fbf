"""Curves where researchers read them: TensorBoard event files (the default), W&B, or none.

A run keeps writing its results to ``metrics.json`` / ``summary.json``, byte for byte as
before; a logger only writes extra files beside them. One interface for every kind:
``scalars(step, {tag: value})`` as the run goes, ``hparams(config, metrics)`` once at the
end (the run's settings and its results, for TensorBoard's HParams tab or W&B's config
and summary), ``close()``. The kind is chosen by name (``--logger none|tensorboard|wandb``)
and its package imported only then.

Where the files go: TensorBoard's event files in the run's directory itself
(``DIR/events.out.tfevents.*``), so ``tensorboard --logdir runs`` shows every run under
its directory name, as with ``SummaryWriter``'s ``runs/<name>``. A fresh run in DIR
replaces the previous run's event files once it has written its results (as it replaces
its metrics.json; a run that fails leaves them, beside its own); a resumed one adds to
them (TensorBoard drops the points a resumed run logs again). W&B runs go in
``DIR/wandb/``, offline unless ``WANDB_MODE`` says otherwise (``wandb sync DIR/wandb/offline-run-*``
uploads them).

Tags: ``train/<loss>`` and ``train/steps_per_s`` while training (step: gradient steps),
``eval/<key>`` for the held-out evaluation (success rate with its Wilson bounds, final
distance), ``online/...`` for the online stage (step: environment steps).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Callable

from ..common.errors import UserError
from ..learners.loop import Progress

LOGGERS = ("none", "tensorboard", "wandb")
DEFAULT_LOGGER = "tensorboard"
LOGGER_HELP = ("where the curves go besides the JSON files: tensorboard (event files in the output directory, "
               "`tensorboard --logdir DIR`), wandb (DIR/wandb, offline unless WANDB_MODE says otherwise; "
               "pip install 'offline_rl_core[wandb]'), or none (default: %(default)s)")
EVENT_FILE_PREFIX = "events.out.tfevents."

_INSTALL = {"tensorboard": "pip install tensorboard",
            "wandb": "pip install 'offline_rl_core[wandb]' (or: pip install wandb)"}


class Logger:
    """Scalars and hyper-parameters of one run; this base class keeps nothing (``--logger none``)."""

    def scalars(self, step: int, values: dict[str, float]) -> None:
        pass

    def hparams(self, config: dict, metrics: dict[str, float]) -> None:
        pass

    def drop_previous(self) -> None:
        """The run is complete: remove the files of the run this fresh one replaces."""

    def close(self) -> None:
        pass

    def __enter__(self) -> "Logger":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def check_logger(kind: str, flag: str = "--logger") -> None:
    """Refuse a logger that cannot be made here, before a run starts (one line: how to install it)."""
    if kind not in LOGGERS:
        raise UserError(f"{flag} must be one of {', '.join(LOGGERS)}, got {kind!r}")
    if kind == "none":
        return
    try:
        if kind == "tensorboard":
            import torch.utils.tensorboard  # noqa: F401 - needs the tensorboard package
        else:
            import wandb  # noqa: F401
    except ImportError:
        raise UserError(f"{flag} {kind}: the {kind} package is not installed; {_INSTALL[kind]}") from None


def open_logger(kind: str, run_dir: str | os.PathLike, name: str, resume: bool = False,
                config: dict | None = None) -> Logger:
    """The logger ``kind`` writing into ``run_dir`` (made if new). ``name``: the run's name in
    W&B; ``resume``: keep the event files already there; ``config``: the settings, known now."""
    check_logger(kind)
    if kind == "none":
        return Logger()
    run_dir = Path(run_dir)
    if kind == "tensorboard":
        return TensorBoardLogger(run_dir, resume)
    run_dir.mkdir(parents=True, exist_ok=True)
    return WandbLogger(run_dir, name, config or {})


class TensorBoardLogger(Logger):
    def __init__(self, run_dir: Path, resume: bool):
        # a fresh run's predecessor: removed once this run is complete (its curves would be
        # drawn over this one's), kept when it fails
        self.previous = [] if resume else sorted(run_dir.glob(EVENT_FILE_PREFIX + "*"))
        self.run_dir = run_dir
        self._writer = None  # made at the first value: a run refused before it writes nothing

    @property
    def writer(self):
        if self._writer is None:
            from torch.utils.tensorboard import SummaryWriter

            self.run_dir.mkdir(parents=True, exist_ok=True)
            # flushed every second: a killed run keeps its curve up to the last second
            self._writer = SummaryWriter(log_dir=str(self.run_dir), flush_secs=1)
        return self._writer

    def scalars(self, step: int, values: dict[str, float]) -> None:
        for tag, value in values.items():
            if value is not None:
                self.writer.add_scalar(tag, float(value), int(step))

    def hparams(self, config: dict, metrics: dict[str, float]) -> None:
        from torch.utils.tensorboard.summary import hparams

        # the run's own event file: TensorBoard's HParams tab joins them with the scalars of
        # the same tags in this run (SummaryWriter.add_hparams would write a sub-run instead)
        for summary in hparams(flat_config(config), {k: float(v) for k, v in metrics.items() if v is not None}):
            self.writer.file_writer.add_summary(summary)

    def drop_previous(self) -> None:
        for old in self.previous:
            old.unlink(missing_ok=True)
        self.previous = []

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()


class WandbLogger(Logger):
    def __init__(self, run_dir: Path, name: str, config: dict):
        import wandb

        self.run = wandb.init(dir=str(run_dir), name=name, config=flat_config(config),
                              mode=os.environ.get("WANDB_MODE", "offline"), reinit="create_new",
                              settings=wandb.Settings(silent=True, console="off"))

    def scalars(self, step: int, values: dict[str, float]) -> None:
        self.run.log({k: float(v) for k, v in values.items() if v is not None}, step=int(step))

    def hparams(self, config: dict, metrics: dict[str, float]) -> None:
        self.run.config.update(flat_config(config), allow_val_change=True)
        self.run.summary.update({k: float(v) for k, v in metrics.items() if v is not None})

    def close(self) -> None:
        self.run.finish()


def flat_config(config: dict, prefix: str = "") -> dict:
    """Nested settings as one level of ``a/b`` keys with values TensorBoard's HParams take
    (bool, int, float, str): None as "None", lists as JSON."""
    out: dict = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flat_config(value, name + "/"))
        elif isinstance(value, (bool, int, float, str)):
            out[name] = value
        else:
            out[name] = "None" if value is None else json.dumps(value, default=str)
    return out


# ------------------------------------------------------------------ what a run logs
def progress_scalars(p: Progress, prefix: str = "train", member: int | None = None) -> dict[str, float]:
    """A training report as tags: each loss (``member``: that run's of an ensemble trained
    together; else their mean) and the steps per second so far."""
    if member is None or p.member_scalars is None:
        values = dict(p.scalars)
    else:
        values = {k: v[member] for k, v in p.member_scalars.items()}
    out = {f"{prefix}/{k}": v for k, v in values.items() if math.isfinite(v)}
    if p.elapsed_s > 0:
        out[f"{prefix}/steps_per_s"] = p.step / p.elapsed_s
    return out


def history_reports(results: list, total: int) -> list[Progress]:
    """The progress reports a job's runs (``TrainResult``s trained together) would have made,
    rebuilt from their logged histories: for runs that could not report as they went (a Ray
    task). No timings: ``elapsed_s`` is 0, so no steps per second are logged."""
    histories = [r.history for r in results]
    names = [k for k in histories[0] if k != "step"]
    reports = []
    for i, step in enumerate(histories[0]["step"]):
        members = {k: [float(h[k][i]) for h in histories] for k in names}
        reports.append(Progress(int(step), total, 0.0, {k: sum(v) / len(v) for k, v in members.items()}, members))
    return reports


def progress_logger(logger: Logger, prefix: str = "train",
                    then: Callable[[Progress], None] | None = None) -> Callable[[Progress], None]:
    """A ``learners.loop`` progress callback that logs each report, then calls ``then``."""
    def report(p: Progress) -> None:
        logger.scalars(p.step, progress_scalars(p, prefix))
        if then is not None:
            then(p)
    return report


EVAL_KEYS = ("success_rate", "wilson_ci_lo", "wilson_ci_hi", "mean_final_dist", "mean_return")


def eval_scalars(result: dict, prefix: str = "eval") -> dict[str, float]:
    """``evaluate_policy``'s result as tags: success rate, its Wilson bounds, distance, return."""
    return {f"{prefix}/{k}": result[k] for k in EVAL_KEYS if result.get(k) is not None}


def online_scalars(learner, weights: dict, env_steps_per_s: float | None) -> dict[str, float]:
    """A weights version (``learner``: the ``learners.online.OnlineLearner`` that cut it) as
    logger tags: the learner's losses, its counts, how many live
    transitions had arrived beyond the ones it was trained on (its age when cut), its
    gradient steps per second of training, and the arm's steps per second."""
    n = learner.n_online
    out = {f"train/{k}": v for k, v in learner.losses.items()}
    out.update({"online/weights_version": weights["weights_version"], "online/updates": learner.updates,
                "online/human_transitions": learner.n_human,
                "online/weights_age_steps": n - weights["trained_through"]})
    if learner.train_seconds > 0:
        out["train/steps_per_s"] = learner.updates / learner.train_seconds
    if env_steps_per_s is not None:
        out["online/env_steps_per_s"] = env_steps_per_s
    return out


def curve_scalars(point: dict) -> dict[str, float]:
    """A point of the learning curve as logger tags: success without intervention with its
    Wilson bounds, final distance, the intervention rate of the window before it."""
    return {"eval/success_rate": point["success"], "eval/wilson_ci_lo": point["ci"][0],
            "eval/wilson_ci_hi": point["ci"][1], "eval/mean_final_dist": point["final_dist"],
            "online/intervention_rate": point["intervention_rate"]}
