"""The best prior from the log (issue 16): the figures of the README's "The best prior".

Two measurements on the REPORT data (datasets of seeds 0, 1, 2 = ``offline-rl collect
--seed S``, bags/mix.db3 for seed 0; the 100 held-out resets 500000 + S .. 500000 + S + 99,
the chapter's five suites of twenty), each appended to the JSON file record by record so
an interrupted run resumes:

``musthold``: per seed, the chapter's AWAC loop (``runs/chapter_loop.py``,
8000 steps) timed in this process with one torch thread and with torch's default, then
``offline-rl train --algo auto`` with its default budget timed as a whole command (start-up,
bag, training, evaluation, files). The run must finish within the faster chapter loop.

``curves``: every learner trained for the same wall time (the default budget: the
chapter's AWAC loop on this machine, ``prior.chapter_awac_seconds``), its steps from its
own measured step rate (``prior.step_rate``); each learner's policy is kept at 1/32, 1/16,
1/8, 1/4, 1/2 and all of the budget (the learners' rates are constant, so the policy at a
fraction of the run is the policy of a run given that fraction of the budget).

``render``: bench/prior_curves.png and the markdown tables (bench/RESULTS.md's "The best
prior", ``results_page``), from the JSON. The JSON also says the commands that filled it and
the machine (one per file).

    flock /tmp/pusher-cpu.lock .venv/bin/python bench/prior_report.py musthold
    flock /tmp/pusher-cpu.lock .venv/bin/python bench/prior_report.py curves
    .venv/bin/python bench/prior_report.py render

``--task NAME`` runs ``curves`` and ``render`` on another task's datasets (``offline-rl collect
--task NAME --seed S``, kept under runs/prior/NAME/) and held-out resets; with ``--validation``
on the VALIDATION data instead (data seeds 10 and 11, resets 600000 + 100 S ..: never the
report's), where a recipe for ``--algo auto`` is chosen:

    .venv/bin/python bench/prior_report.py curves --task pusher_push --validation \
        --json bench/pusher_push_validation.json --fractions 0.25 0.5 1
    .venv/bin/python bench/prior_report.py curves --task pusher_push --json bench/pusher_push_report.json
    .venv/bin/python bench/prior_report.py render --task pusher_push --json bench/pusher_push_report.json \
        --png bench/pusher_push_curves.png
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

from offline_rl_core.benchmarks.harness import add_run_facts
from offline_rl_core.common.atomic import write_json_atomic
from offline_rl_core.data.bag import read_transitions
from offline_rl_core.evaluation.rollouts import rollout_task
from offline_rl_core.evaluation.stats import newcombe_diff_ci, wilson_ci
from offline_rl_core.learners import TrainConfig, train
from offline_rl_core.runs import chapter_loop as chapter
from offline_rl_core.runs.prior import chapter_awac_seconds, plan_training, step_rate, steps_for_budget
from offline_rl_core.task.spec import DEFAULT_TASK, load_task
from results_page import curves_table, musthold_table, task_curves_table

ROOT = Path(__file__).resolve().parents[1]
SEEDS = (0, 1, 2)
VALIDATION_SEEDS = (10, 11)  # data seeds of the validation data (prior_selection.py's)
VALIDATION_RESETS = 600000  # + 100 * data seed: never a held-out reset (500000 + seed + 0..99)
FRACTIONS = (1 / 32, 1 / 16, 0.125, 0.25, 0.5, 1.0)
LEARNERS = {  # label -> TrainConfig overrides (the chapter's hyper-parameters otherwise)
    "BC": {"algo": "bc"},
    "filtered BC (top 10 %)": {"algo": "filtered_bc"},
    "AWAC": {"algo": "awac"},
    "IQL": {"algo": "iql"},
}


TASK = DEFAULT_TASK  # --task
VALIDATION = False  # --validation


def bag_for(seed: int, expert_frac: float) -> Path:
    if seed == 0 and expert_frac == 0.3 and TASK == DEFAULT_TASK:
        return ROOT / "bags" / "mix.db3"
    folder = ROOT / "runs" / "prior" / ("" if TASK == DEFAULT_TASK else TASK) / "bags"
    path = folder / f"mix_s{seed}_e{expert_frac}.db3"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, "-m", "offline_rl_core", "collect", "--task", TASK, "--episodes", "200",
                        "--expert-frac", str(expert_frac), "--seed", str(seed), "--out", str(path)], check=True)
    return path


def resets(seed: int) -> range:
    if VALIDATION:
        return range(VALIDATION_RESETS + 100 * seed, VALIDATION_RESETS + 100 * seed + 100)
    return range(500000 + seed, 500000 + seed + 100)


def score(act, seed: int) -> dict:
    r = rollout_task(TASK, act, resets(seed))
    lo, hi = wilson_ci(r.successes, r.episodes)
    return {"successes": r.successes, "episodes": r.episodes, "success_rate": r.success_rate,
            "wilson": [round(lo, 4), round(hi, 4)], "mean_final_dist": round(r.mean_final_dist, 6)}


class Store:
    def __init__(self, path: Path):
        self.path = path
        self.data = json.loads(path.read_text()) if path.exists() else {}

    def measuring(self) -> None:
        """Before this command adds figures: it joins the file's commands (same machine only)."""
        add_run_facts(self.data)

    def has(self, group: str, key: str) -> bool:
        return key in self.data.get(group, {})

    def put(self, group: str, key: str, record: dict) -> None:
        self.data.setdefault(group, {})[key] = record
        write_json_atomic(self.path, self.data)


def musthold(store: Store, expert_frac: float) -> None:
    # the default budget and the step rate are measured once per machine (cached): do it
    # here, not inside the first timed command
    _, plan = plan_training(read_transitions(bag_for(0, expert_frac)), TrainConfig(), True, None, None, print)
    store.data.setdefault("calibration", {})[f"e{expert_frac}"] = plan
    for seed in SEEDS:
        key = f"seed{seed}_e{expert_frac}"
        if store.has("musthold", key):
            continue
        bag = bag_for(seed, expert_frac)
        tensors = chapter.dataset_tensors(read_transitions(bag))
        chapter_s = {}
        default_threads = torch.get_num_threads()
        for threads in sorted({1, default_threads}, reverse=seed % 2 == 1):  # alternate which goes first
            torch.set_num_threads(threads)
            torch.manual_seed(seed)
            t0 = time.perf_counter()
            chapter.train_awac(tensors, chapter.ChapterSettings())
            chapter_s[str(threads)] = round(time.perf_counter() - t0, 2)
        torch.set_num_threads(default_threads)
        out = ROOT / "runs" / "prior" / f"auto_{key}"
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "offline_rl_core", "train", "--bag", str(bag), "--algo", "auto",
                        "--seed", str(seed), "--eval-seed", str(500000 + seed), "--eval-episodes", "100",
                        "--out", str(out)], check=True)
        command_s = round(time.perf_counter() - t0, 2)
        metrics = json.loads((out / "metrics.json").read_text())
        ckpt = torch.load(out / "policy.pt", weights_only=True)
        ref = min(chapter_s.values())
        store.put("musthold", key, {
            "seed": seed, "expert_frac": expert_frac, "chapter_awac_s": chapter_s, "chapter_ref_s": ref,
            "auto_command_s": command_s, "auto_train_s": ckpt["train_seconds"], "within": command_s <= ref,
            "algorithm": metrics["algorithm"], "steps": metrics["steps"], "plan": metrics["plan"],
            "eval": metrics["eval"]})
        print(f"seed {seed}: chapter AWAC loop {chapter_s} s; auto {command_s} s whole command "
              f"({ckpt['train_seconds']} s training, {metrics['steps']} steps of {metrics['algorithm']}); "
              f"success {metrics['eval']['success_rate']:.2f}", flush=True)


def curves(store: Store, expert_frac: float, learners: list[str], fractions=FRACTIONS) -> None:
    task = load_task(TASK)
    store.data.setdefault("task", {"name": task.name, "digest": task.digest,
                                   "resets": "validation" if VALIDATION else "held-out"})
    for seed in VALIDATION_SEEDS if VALIDATION else SEEDS:
        data = read_transitions(bag_for(seed, expert_frac))
        budget = chapter_awac_seconds(data, print)
        for label in learners:
            key = f"{label}|seed{seed}_e{expert_frac}"
            if store.has("curves", key):
                continue
            if label == "auto":
                cfg, plan = plan_training(data, TrainConfig(), True, budget, None, task=task)
                # a constant-rate run passes through the shorter budgets' runs: keep its policy on the way
                assert cfg.lr_schedule == "constant", "auto with a schedule needs one run per budget"
            else:
                cfg = TrainConfig(**LEARNERS[label])
            rate = step_rate(cfg, data, print, task)
            marks = {steps_for_budget(budget * f, rate): f for f in fractions}
            kept = {}
            run = replace(cfg, steps=max(marks), log_every=100)
            t0 = time.perf_counter()
            result = train(data, run, seed, snapshot=lambda step, elapsed, policy_state: kept.__setitem__(
                step, (elapsed, policy_state(0))) if step in marks else None, task=task)
            wall = time.perf_counter() - t0
            points = []
            for steps, (elapsed, state) in sorted(kept.items()):
                policy = type(result.policy)(dict(result.checkpoint, policy_state=state))
                points.append({"fraction": marks[steps], "budget_s": round(budget * marks[steps], 3), "steps": steps,
                               "nominal_s": round(steps / rate, 3), "train_s": round(elapsed, 3),
                               "algorithm": cfg.algo, **score(policy.act, seed)})
            store.put("curves", key, {"label": label, "seed": seed, "expert_frac": expert_frac, "budget_s": budget,
                                      "steps_per_s": rate, "algorithm": cfg.algo, "train_wall_s": round(wall, 2),
                                      "resets": [resets(seed)[0], resets(seed)[-1]], "points": points,
                                      **({"plan": plan} if label == "auto" else {})})
            print(f"seed {seed} {label}: " + ", ".join(f"{p['steps']} steps {p['success_rate']:.2f}" for p in points),
                  flush=True)


def render(store: Store, out_png: Path, expert_frac: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by_label: dict[str, list] = {}
    for rec in store.data.get("curves", {}).values():
        if rec["points"] and rec["expert_frac"] == expert_frac:
            by_label.setdefault(rec["label"], []).append(rec)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for label, recs in by_label.items():
        fr = sorted({p["fraction"] for r in recs for p in r["points"]})
        xs, ys, lo, hi = [], [], [], []
        for f in fr:
            pts = [p for r in recs for p in r["points"] if p["fraction"] == f]
            s, n = sum(p["successes"] for p in pts), sum(p["episodes"] for p in pts)
            a, b = wilson_ci(s, n)
            xs.append(sum(p["nominal_s"] for p in pts) / len(pts))
            ys.append(s / n)
            lo.append(s / n - a)
            hi.append(b - s / n)
        ax.errorbar(xs, ys, yerr=[lo, hi], marker="o", capsize=3, label=label)
    budget = next(iter(by_label.values()))[0]["budget_s"]
    ax.axvline(budget, color="grey", ls=":", lw=1)
    ax.text(budget, 0.02, " chapter's AWAC loop", color="grey", fontsize=8)
    ax.set_xlabel("seconds of training (steps / measured step rate, one thread)")
    ax.set_ylabel("success, 3 seeds x 100 held-out rollouts")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_xscale("log")
    ax.set_title(f"{'' if TASK == DEFAULT_TASK else TASK + ': '}success against training time, "
                 f"{expert_frac:.0%} expert episodes (Wilson 95 %)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out_png, dpi=120)
    print(f"wrote {out_png}")
    if TASK == DEFAULT_TASK:
        print(curves_table(store.data.get("curves", {}), expert_frac))
        print()
        print(musthold_table(store.data.get("musthold", {})))
        return
    print(task_curves_table(store.data.get("curves", {}), expert_frac))
    for key, rec in sorted(store.data.get("musthold", {}).items()):
        print(f"{key}: chapter {rec['chapter_awac_s']} s, auto {rec['auto_command_s']} s "
              f"({rec['auto_train_s']} s training, {rec['steps']} steps), within {rec['within']}, "
              f"success {rec['eval']['success_rate']}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("musthold", "curves", "render"))
    ap.add_argument("--json", default=str(ROOT / "bench" / "prior_report.json"))
    ap.add_argument("--expert-frac", type=float, default=0.3)
    ap.add_argument("--learners", nargs="*", default=[*LEARNERS, "auto"])
    ap.add_argument("--png", default=str(ROOT / "bench" / "prior_curves.png"))
    ap.add_argument("--task", default=DEFAULT_TASK, help="curves and render on this task's data and resets")
    ap.add_argument("--validation", action="store_true",
                    help="the validation data and resets (data seeds 10, 11; resets 600000 + 100 x seed)")
    ap.add_argument("--fractions", type=float, nargs="*", default=list(FRACTIONS),
                    help="budget fractions at which each learner's policy is scored")
    args = ap.parse_args()
    global TASK, VALIDATION
    TASK, VALIDATION = args.task, args.validation
    store = Store(Path(args.json))
    if args.what == "musthold":
        if TASK != DEFAULT_TASK or VALIDATION:
            ap.error("musthold is the chapter's task's, on its report data")
        store.measuring()
        musthold(store, args.expert_frac)
    elif args.what == "curves":
        store.measuring()
        store.data.setdefault("command", "python bench/prior_report.py " + " ".join(sys.argv[1:]))
        curves(store, args.expert_frac, args.learners, tuple(args.fractions))
    else:
        render(store, Path(args.png), args.expert_frac)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
