"""What bounds the HIL-SERL stage on pusher7_reach (issue 23): the in-process stage on seed 0
at the full budget (20,000 environment steps) with one setting changed at a time.

    .venv/bin/python bench/pusher7_online_probes.py [--variants NAME ...] [--out runs/p7-probes]
                                                    [--json bench/pusher7_online_probes.json]

The stage is ``runs.online_loop.run_online`` (what ``offline-rl hil --online --in-process``
runs): the ``--algo auto`` prior of bench/pusher7_online.py (trained on the task's recorded mix
``offline-rl collect --task pusher7_reach --episodes 200 --expert-frac 0.3 --seed 0``), SAC
with the scripted corrector, lockstep, the deterministic policy scored on the 100 held-out
resets every 2,500 steps. Each variant changes one thing against ``baseline`` (the stage's
defaults); a variant whose record is in the JSON is not run again. The final policy's
failures are looked at too (``failures``: how near each failed episode came). Writes the JSON (each
variant's curve, counts, settings, the command and the machine, with the digest of the task
it ran on: once the task file changes, earlier variants stay as ``NAME@DIGEST``) and prints the
table of bench/RESULTS.md's section.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from offline_rl_core.benchmarks.harness import run_facts
from offline_rl_core.common.atomic import write_json_atomic
from offline_rl_core.data.bag import read_transitions
from offline_rl_core.learners.config import TrainConfig
from offline_rl_core.learners.online import OnlineSettings
from offline_rl_core.runs.online_loop import OnlineRunConfig, run_online
from offline_rl_core.serving.checkpoint import load_checkpoint
from offline_rl_core.common.seeds import HELD_OUT
from offline_rl_core.serving.policy import LoadedPolicy
from offline_rl_core.task.corrector import CorrectorParams
from offline_rl_core.task.envs import make_env
from offline_rl_core.task.spec import load_task
from pusher7_online import mark_older_task_records
from results_page import probes_table

TASK = "pusher7_reach"
# name -> (what it changes, the OnlineRunConfig / TrainConfig / OnlineSettings / CorrectorParams overrides)
VARIANTS = {
    "baseline": ("the stage's defaults: utd 2, half of each batch offline, alpha 0.01, gamma 0.99", {}),
    "end_on_success": ("an episode ends where the simulator judges success (HIL-SERL's rule)",
                       {"run": {"end_on_success": True}}),
    "utd4": ("4 gradient steps per environment step", {"online": {"utd": 4}}),
    "alpha0.001": ("a tenth of the entropy weight", {"train": {"alpha": 0.001}}),
    "target_entropy-7": ("the entropy weight tuned toward -7 (one nat per joint below zero)",
                         {"train": {"target_entropy": -7.0}}),
    "offline0.25": ("a quarter of each batch offline", {"online": {"offline_ratio": 0.25}}),
    "offline0.25_gamma0.97": ("a quarter offline and gamma 0.97",
                              {"online": {"offline_ratio": 0.25}, "train": {"gamma": 0.97}}),
    "corrector_progress0.01": ("the corrector takes over when the fingertip gained under 1 cm in 8 steps "
                               "(a person grabbing an arm that crawls)", {"corrector": {"min_progress": 0.01}}),
    "corrector_progress0.01_offline0.25": ("both of the above",
                                           {"corrector": {"min_progress": 0.01}, "online": {"offline_ratio": 0.25}}),
    "normalize_obs": ("actor and critics on z-scored observations (the offline data's statistics, as the "
                      "auto prior was trained), folded into every weights version", {"train": {"normalize_obs": True}}),
    "normalize_obs_corrector_progress0.01_offline0.25": (
        "z-scored observations, the crawling-arm corrector and a quarter of each batch offline",
        {"train": {"normalize_obs": True}, "corrector": {"min_progress": 0.01}, "online": {"offline_ratio": 0.25}}),
    "normalize_obs_imitate_expert": (
        "z-scored observations and the actor's BC term also on the mix's expert episodes",
        {"train": {"normalize_obs": True}, "online": {"imitate_expert": True}}),
    "normalize_obs_alpha0.003": ("z-scored observations and a third of the entropy weight",
                                 {"train": {"normalize_obs": True, "alpha": 0.003}}),
    "imitate_expert": ("the actor's BC term also on the mix's expert episodes (TD3+BC's anchor on demonstrations)",
                       {"online": {"imitate_expert": True}}),
    **{f"normalize_obs_imitate_expert_bc{w:g}{'_lr_decay' if decay else ''}": (
        f"z-scored observations, the expert's episodes imitated, BC weight {w:g}"
        + (", learning rates along a cosine to zero over the budget" if decay else ""),
        {"train": {"normalize_obs": True, "bc_weight": float(w)},
         "online": {"imitate_expert": True, **({"lr_decay_steps": "budget"} if decay else {})}})
       for w, decay in ((3, True), (10, True), (30, False), (30, True), (100, True), (300, True))},
    "normalize_obs_imitate_expert_bc100_lr_decay_offline0.25": (
        "z-scored observations, the expert's episodes imitated, BC weight 100, the decay, and a quarter of each "
        "batch offline (more of the person's corrections in each batch)",
        {"train": {"normalize_obs": True, "bc_weight": 100.0},
         "online": {"imitate_expert": True, "lr_decay_steps": "budget", "offline_ratio": 0.25}}),
    **{f"normalize_obs_{'imitate_expert_' if imitate else ''}bc{w:g}_lr_decay_stick": (
        "z-scored observations, " + ("the expert's episodes imitated, " if imitate else "") + f"BC weight {w:g}, the decay, "
        "and the corrector steering the fingertip straight at the goal (a Cartesian stick) instead of the expert's "
        "joint-space swing",
        {"train": {"normalize_obs": True, "bc_weight": float(w)}, "corrector": {"steer": "stick"},
         "online": {"imitate_expert": imitate, "lr_decay_steps": "budget"}})
       for w, imitate in ((30, True), (100, True), (100, False))},
    **{f"normalize_obs_imitate_expert_bc100_lr_decay_offline{r:g}{'_utd4' if utd == 4 else ''}": (
        f"z-scored observations, the expert's episodes imitated, BC weight 100, the decay, {share} of each batch "
        "offline" + (" and 4 gradient steps per environment step" if utd == 4 else ""),
        {"train": {"normalize_obs": True, "bc_weight": 100.0},
         "online": {"imitate_expert": True, "lr_decay_steps": "budget", "offline_ratio": r, "utd": utd}})
       for r, share, utd in ((0.25, "a quarter", 4), (0.1, "a tenth", 2))},
    "normalize_obs_imitate_expert_bc100_lr_decay_offline0.25_noise0.2": (
        "z-scored observations, the expert's episodes imitated, BC weight 100, the decay, a quarter of each batch "
        "offline, and a shaky hand: Gaussian noise of std 0.2 on the corrector's actions (its states' velocities "
        "then tell less of the next action, DART's remedy for an imitator that copies its own motion)",
        {"train": {"normalize_obs": True, "bc_weight": 100.0}, "corrector": {"noise": 0.2},
         "online": {"imitate_expert": True, "lr_decay_steps": "budget", "offline_ratio": 0.25}}),
    "normalize_obs_imitate_expert_bc100_lr_decay_offline0.25_stick": (
        "z-scored observations, the expert's episodes imitated, BC weight 100, the decay, a quarter of each batch "
        "offline and the corrector steering the fingertip straight at the goal",
        {"train": {"normalize_obs": True, "bc_weight": 100.0}, "corrector": {"steer": "stick"},
         "online": {"imitate_expert": True, "lr_decay_steps": "budget", "offline_ratio": 0.25}}),
}


def config_of(name: str, seed: int, env_steps: int) -> OnlineRunConfig:
    over = VARIANTS[name][1]
    return OnlineRunConfig(env_steps=env_steps, seed=seed, task=TASK, eval_every=2500,
                           train=TrainConfig(**{"algo": "sac", **over.get("train", {})}),
                           settings=OnlineSettings(**{k: env_steps if v == "budget" else v  # the decay: over the run
                                                      for k, v in over.get("online", {}).items()}),
                           corrector=CorrectorParams(**over.get("corrector", {})), **over.get("run", {}))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--env-steps", type=int, default=20_000)
    p.add_argument("--out", default="runs/p7-probes", help="the mix and the prior (made if missing)")
    p.add_argument("--json", default="bench/pusher7_online_probes.json")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    offline_rl = [sys.executable, "-m", "offline_rl_core"]
    digest = load_task(TASK).digest  # a changed task file records a new mix and trains a new prior
    bag, prior = out / f"pusher7-{digest}.db3", out / f"prior-{digest}" / "policy.pt"
    if not bag.exists():
        subprocess.run([*offline_rl, "collect", "--task", TASK, "--episodes", "200", "--expert-frac", "0.3",
                        "--seed", "0", "--out", str(bag)], check=True)
    if not prior.exists():  # the stage's own prior: offline-rl hil --online trains it so
        subprocess.run([*offline_rl, "train", "--task", TASK, "--bag", str(bag), "--algo", "auto", "--seed",
                        str(args.seed), "--eval-episodes", "0", "--logger", "none", "--out", str(prior.parent)],
                       check=True)
    path = Path(args.json)
    import json

    data = json.loads(path.read_text()) if path.exists() else {"task": TASK, "variants": {}}
    data.update(run_facts())
    mark_older_task_records(data["variants"], data.setdefault("variant_task_digests", {}), digest,
                            data.get("task_digest"))
    data["task_digest"] = digest
    offline, checkpoint = read_transitions(bag), load_checkpoint(prior)
    for name in args.variants:
        if name in data["variants"]:
            continue
        print(f"{name}: {VARIANTS[name][0]}", flush=True)
        cfg = config_of(name, args.seed, args.env_steps)
        result = run_online(offline, checkpoint, cfg, log=lambda s: print(s, flush=True))
        weights = result.pop("final_weights")
        (out / name).mkdir(exist_ok=True)
        torch.save(weights, out / name / "policy.pt")
        data["variants"][name] = {"changes": VARIANTS[name][0], "seed": args.seed, **result,
                                  "failures": failures(weights),
                                  "settings": {"online": asdict(cfg.settings), "corrector": asdict(cfg.corrector),
                                               "end_on_success": cfg.end_on_success}}
        data["variant_task_digests"][name] = digest
        write_json_atomic(path, data)
    print(probes_table(data))
    return 0


def failures(weights: dict, first_seed: int = HELD_OUT, episodes: int = 100) -> dict:
    """How the final deterministic policy fails on the held-out resets: each failed episode's
    closest approach and final distance (m), and its fingertip's mean speed over the last 10
    steps (m per step): a policy that gets near and then crawls, or one that never gets near."""
    task = load_task(TASK)
    policy, env = LoadedPolicy(weights), make_env(task, terminate_on_success=False)
    failed = []
    for reset in range(first_seed, first_seed + episodes):
        obs, done, dist = env.reset(reset), False, []
        while not done:
            obs, _, done, info = env.step(policy.act(obs))
            dist.append(info["dist"])
        if not info["success"]:
            failed.append({"reset": reset, "closest": round(min(dist), 4), "final": round(dist[-1], 4),
                           "last_10_steps_m_per_step": round(abs(dist[-1] - dist[-11]) / 10, 5)})
    closest = np.array([f["closest"] for f in failed]) if failed else np.zeros(0)
    return {"count": len(failed), "within_0.1m": int((closest < 0.1).sum()),
            "closest_median": round(float(np.median(closest)), 4) if failed else None, "episodes": failed}


if __name__ == "__main__":
    sys.exit(main())
