"""Figures for training and evaluation (matplotlib, Agg backend, written atomically)."""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the backend)

from ..common.atomic import atomic_path  # noqa: E402


def _save_atomic(fig, path: str | os.PathLike) -> Path:
    try:
        with atomic_path(path, suffix=Path(path).suffix or ".png") as tmp:
            # A fixed Software tag and no date keep the PNG bytes stable across runs.
            fig.savefig(tmp, dpi=110, metadata={"Software": "pusher-rl"})
    finally:
        plt.close(fig)
    return Path(path)


def plot_training_curve(history: dict[str, list[float]], path: str | os.PathLike, title: str | None = None) -> Path:
    """Loss curves against step, one panel per logged scalar ('step' is the x axis).

    Q-valued scalars (names containing 'q') are drawn on a linear axis, losses on a
    log axis when they stay positive.
    """
    steps = history.get("step", [])
    keys = [k for k in history if k != "step" and len(history[k]) == len(steps)]
    if not keys:
        raise ValueError("history has no scalar series besides 'step'")
    fig, axes = plt.subplots(len(keys), 1, figsize=(6.4, 1.9 * len(keys) + 0.6), sharex=True, squeeze=False)
    for ax, key in zip(axes[:, 0], keys):
        values = history[key]
        ax.plot(steps, values, lw=1.2)
        ax.set_ylabel(key)
        if "q" not in key.lower() and min(values) > 0:
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("gradient step")
    if title:
        axes[0, 0].set_title(title)
    fig.tight_layout()
    return _save_atomic(fig, path)


def plot_success_bars(summary_rows: list[dict], path: str | os.PathLike, title: str | None = None) -> Path:
    """Grouped bars of BC vs offline success per row, with Wilson 95 % error bars.

    Each row: ``label``, ``bc_success_rate``, ``bc_ci`` (lo, hi), ``offline_success_rate``,
    ``offline_ci`` (lo, hi), and optionally ``offline_label`` (legend name, e.g. 'AWAC').
    """
    if not summary_rows:
        raise ValueError("no rows to plot")
    labels = [str(r["label"]) for r in summary_rows]
    width = 0.38
    xs = range(len(summary_rows))
    fig, ax = plt.subplots(figsize=(max(4.0, 1.3 * len(labels) + 1.5), 3.6))
    arms = (("bc", "BC", -width / 2, "#8c8c8c"), ("offline", summary_rows[0].get("offline_label", "offline"), width / 2, "#1f77b4"))
    for key, name, shift, color in arms:
        rates = [r[f"{key}_success_rate"] for r in summary_rows]
        lo = [max(0.0, rate - r[f"{key}_ci"][0]) for rate, r in zip(rates, summary_rows)]
        hi = [max(0.0, r[f"{key}_ci"][1] - rate) for rate, r in zip(rates, summary_rows)]
        ax.bar([x + shift for x in xs], rates, width, yerr=[lo, hi], capsize=4, label=name, color=color)
    ax.set_xticks(list(xs), labels)
    ax.set_ylabel("success rate (Wilson 95 % CI)")
    ax.set_ylim(0.0, 1.0)
    ax.legend(frameon=False)
    ax.grid(axis="y", alpha=0.3)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return _save_atomic(fig, path)


def plot_arm_success(rows: list[dict], path: str | os.PathLike, title: str | None = None) -> Path:
    """One bar per arm: its success rate with Wilson 95 % error bars; the baseline grey.

    Each row: ``label``, ``rate``, ``ci`` (lo, hi) and ``baseline`` (bool).
    """
    if not rows:
        raise ValueError("no rows to plot")
    fig, ax = plt.subplots(figsize=(max(4.0, 0.9 * len(rows) + 1.5), 3.8))
    xs = list(range(len(rows)))
    rates = [r["rate"] for r in rows]
    lo = [max(0.0, rate - r["ci"][0]) for rate, r in zip(rates, rows)]
    hi = [max(0.0, r["ci"][1] - rate) for rate, r in zip(rates, rows)]
    colors = ["#8c8c8c" if r.get("baseline") else "#1f77b4" for r in rows]
    ax.bar(xs, rates, 0.6, yerr=[lo, hi], capsize=4, color=colors)
    ax.set_xticks(xs, [str(r["label"]) for r in rows], rotation=30 if len(rows) > 4 else 0,
                  ha="right" if len(rows) > 4 else "center")
    ax.set_ylabel("success rate (Wilson 95 % CI)")
    ax.set_ylim(0.0, 1.0)
    ax.grid(axis="y", alpha=0.3)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return _save_atomic(fig, path)
