"""What bounds learning pusher_push from corrections: behaviour cloning of the scripted expert
alone (on logs of N expert episodes, at the actor's width), full DAgger, and the stage itself,
each scored on 100 held-out resets.

The online stage's actor learns a person's (here the scripted corrector's) actions by a BC
term beside its SAC objective. How well an MLP of the stage's width can copy the expert,
given far more clean demonstrations than a session sees, bounds what that term can give:

  .venv/bin/python bench/push_bound.py --variants wave direction rate20 --json bench/pusher_push_bound.json

A cell already in the --json file, measured on the same task file with the same steps, is
kept, not trained again. ``--online-steps N`` also runs the online stage itself on each
variant (``offline-rl hil --online --in-process``, seed 0 or ``--seed``, from the variant's auto prior on
its own 200-episode mix, 30 % expert, with pusher7_reach's anchor: STAGE), to set beside
what imitation alone gives (``--stage-width W``: from an auto prior W wide, fine-tuned at that
width); ``--patience K --hold-steps M --grace-steps G`` set its scripted
corrector's rule, ``--bc-weight W`` its actor's BC weight, ``--no-explore`` its acting on the
policy's mean and ``--action-labels`` the corrector's labels of the states it leaves to the policy
(each run an entry of its own); ``--over-ros`` runs it over ROS on raw topics (``--from-topics``)
instead of in process.

For each task variant, log size and width: `offline-rl collect --task T --episodes N
--expert-frac 1 --seed 1000` (resets 1000.., far from the held-out 500000..), then `offline-rl
train --algo bc --normalize-obs --hidden W --steps S`, then the deterministic policy on reset
seeds 500000..500099, each failure put in one bin:

- ``near``: the puck ends within 3 x success_within of the goal (precision);
- ``pushed``: the puck moved (more than 3 mm) but ends further away;
- ``untouched``: the puck never moved.

Variants (copies of the task file written with its model into the work folder):
``pusher_push`` as shipped; ``wave``, pusher_push as first shipped (the wave expert at 50 Hz,
bench/push_tasks/pusher_push_wave.yaml, digest f371e75b24e83718), of which every other variant
is an edit (so each keeps the task file its figures were measured on); ``direction``: the
observation adds ``direction: [puck, fingertip]`` and ``direction: [goal, puck]`` (the feature
that lifted pusher7_reach);
``rate20``: the arm commanded at 20 Hz instead of 50 (control_period 0.05 s, frame_skip 10,
60 steps: the same 3 s), as HIL-SERL's arms act at 10 Hz; ``direction_rate20``: both;
``direction_frame``: the directions and ``along_across: [fingertip, puck, goal]`` (the
fingertip seen from the puck, along and across its line to the goal); ``direction_frame_rate20``:
those at 20 Hz; ``direction_frame_elbow_rate20``: besides, where the forearm starts (``elbow``,
the body link2) seen from the puck and along its line to the goal; ``direction_frame_table_rate20``:
besides, the puck and the goal on the table (``vector: puck``, ``vector: goal``); ``orbit``:
the scripted expert (the labels) goes round the puck in the push line's frame
(``sim.push.approach: orbit``) instead of through joint space; ``orbit_direction_frame_rate20``:
that expert on ``direction_frame_rate20`` (the shipped pusher_push but for its name).

``--dagger ROUNDS`` measures the most a corrector's labels can teach an actor of each width:
DAgger with every state labelled, where a person takes over only some. BC (deterministic,
fp32) on ``--dagger-demos`` expert episodes, then each round the policy acts for
``--dagger-round-steps`` environment steps (whole episodes) while the expert labels every
state it visits, and BC goes on from the last weights on all labels so far for
``--dagger-steps``; success on the held-out resets every third round, against environment
steps (the demonstrations' included), as the online stage's budget counts them:

  .venv/bin/python bench/push_bound.py --variants wave direction_frame direction_frame_rate20 \
      --episodes --widths 256 --dagger 16 --json bench/pusher_push_dagger.json
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import offline_rl_core.runs  # noqa: F401 - the speed layer, registered onto the learners as a run has it
from offline_rl_core.benchmarks.harness import add_run_facts
from offline_rl_core.common.atomic import write_text_atomic
from offline_rl_core.common.seeds import HELD_OUT
from offline_rl_core.data.transitions import SOURCE_EXPERT, Transitions
from offline_rl_core.evaluation.rollouts import rollout_expert, rollout_task, round6
from offline_rl_core.evaluation.stats import wilson_ci
from offline_rl_core.serving.policy import load_policy
from offline_rl_core.learners.config import TrainConfig
from offline_rl_core.learners.loop import train as loop_train
from offline_rl_core.task.envs import expert_action, make_env
from offline_rl_core.task.spec import load_task

BUILTIN = Path(__file__).resolve().parents[1] / "offline_rl_core" / "task" / "builtin"
# pusher_push as first shipped (the wave, 50 Hz, the first observation; digest f371e75b24e83718):
# the variants are edits of it, so each keeps the task file (and digest) it was measured on
WAVE = Path(__file__).resolve().parent / "push_tasks" / "pusher_push_wave.yaml"
COLLECT_SEED = 1000
MOVED_M = 0.003  # the puck moved this far: the arm pushed it
NEAR = 3.0  # a failure within NEAR x success_within of the goal is one of precision
DAGGER_STEPS = 5000  # BC steps per DAgger round (an entry with others is keyed by them)
DIRECTIONS = ("  - difference: [goal, puck]        # where it should go\n",
              "  - direction: [puck, fingertip]\n  - direction: [goal, puck]\n")  # added after the first


# variant -> the edits of the first pusher_push (WAVE) that make it (each must match it once)
VARIANTS = {
    "direction": [DIRECTIONS],
    "rate20": [("control_period: 0.02", "control_period: 0.05"), ("  frame_skip: 4\n", "  frame_skip: 10\n"),
               ("  max_steps: 150", "  max_steps: 60")],
}
VARIANTS["direction_rate20"] = VARIANTS["direction"] + VARIANTS["rate20"]
VARIANTS["direction_frame"] = [(DIRECTIONS[0], DIRECTIONS[1] + "  - along_across: [fingertip, puck, goal]\n")]
VARIANTS["direction_frame_rate20"] = VARIANTS["direction_frame"] + VARIANTS["rate20"]
PUCK_POINT = "  puck:                             # as a tracker publishes it"
ELBOW_POINT = (PUCK_POINT, "  elbow:                            # where the forearm starts\n"
               "    kinematics: body:link2\n    axes: [x, y]\n" + PUCK_POINT)
# where the puck and the goal are on the table (the arm's base frame): the expert's way around the
# puck is planned in joint space, so it depends on where the puck is, not only on where it is
# seen from the fingertip
VARIANTS["direction_frame_table_rate20"] = [
    (DIRECTIONS[0], DIRECTIONS[1] + "  - along_across: [fingertip, puck, goal]\n  - vector: puck\n"
     "  - vector: goal\n")] + VARIANTS["rate20"]
# the scripted expert goes round the puck in the push line's frame instead of through joint space
ORBIT = [("    standoff: 0.02\n", "    standoff: 0.02\n    approach: orbit\n")]
VARIANTS["orbit"] = ORBIT
VARIANTS["orbit_direction_frame_rate20"] = VARIANTS["direction_frame_rate20"] + ORBIT
VARIANTS["direction_frame_elbow_rate20"] = [
    (DIRECTIONS[0], DIRECTIONS[1] + "  - along_across: [fingertip, puck, goal]\n  - difference: [puck, elbow]\n"
     "  - along_across: [elbow, puck, goal]\n"), ELBOW_POINT] + VARIANTS["rate20"]


def variant_task(name: str, work: Path) -> str:
    """The task file (or built-in name) of a variant."""
    if name == "pusher_push":
        return name
    if name != "wave" and name not in VARIANTS:
        raise SystemExit(f"push_bound: unknown variant {name!r} (pusher_push, wave, {', '.join(VARIANTS)})")
    text = WAVE.read_text()  # ``wave``: as first shipped, its name (and so its digest) unchanged
    if name != "wave":
        text = text.replace("name: pusher_push\n", f"name: pusher_push_{name}\n")
    for old, new in VARIANTS.get(name, ()):
        if text.count(old) != 1:
            raise SystemExit(f"push_bound: {WAVE.name} no longer holds {old.strip()!r} once; update VARIANTS")
        text = text.replace(old, old + new if old == DIRECTIONS[0] else new)  # features go after the line
    folder = work / "tasks"
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copy(BUILTIN / "pusher_push.xml", folder / "pusher_push.xml")
    path = folder / f"pusher_push_{name}.yaml"
    path.write_text(text)
    return str(path)


def offline_rl(*args: str) -> None:
    done = subprocess.run([sys.executable, "-m", "offline_rl_core", *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"push_bound: offline-rl {' '.join(args)} failed:\n{done.stderr[-2000:]}")


def score(policy_path: Path, task, episodes: int) -> dict:
    """The deterministic policy on the held-out resets, each failure binned (module docstring)."""
    return score_policy(load_policy(policy_path, task), task, episodes)


def score_policy(policy, task, episodes: int) -> dict:
    env = make_env(task)
    bins = {"success": 0, "near": 0, "pushed": 0, "untouched": 0}
    finals = []
    for seed in range(HELD_OUT, HELD_OUT + episodes):
        obs, done, moved = env.reset(seed), False, False
        start = env.puck.copy()
        while not done:
            obs, _, done, info = env.step(np.asarray(policy.act(obs[None]))[0])
            moved = moved or float(np.linalg.norm(env.puck - start)) > MOVED_M
        finals.append(info["dist"])
        bins["success" if info["success"] else "near" if info["dist"] < NEAR * task.reward.success_within
             else "pushed" if moved else "untouched"] += 1
    lo, hi = wilson_ci(bins["success"], episodes)
    return {"task_digest": task.digest, "success": round6(bins["success"] / episodes), "ci": [round6(lo), round6(hi)],
            "failures": {k: v for k, v in bins.items() if k != "success"},
            "final_dist_m": {"median": round6(np.median(finals)), "p75": round6(np.percentile(finals, 75))}}


# the learner's anchor that carried pusher7_reach: actor and critic on z-scored observations, the
# BC term (weight 100) also on the log's expert episodes, the rates decaying over the budget, a
# quarter of each batch from the log (bench/push_online.py runs every arm with it too)
ANCHOR = ("--normalize-obs", "--imitate-expert", "--bc-weight", "100", "--lr-decay", "--offline-ratio", "0.25")
STAGE = ANCHOR + ("--seed", "0")


# settings of a stage run that may differ from STAGE and the stage's defaults: (flag, the summary's
# config key); a later flag wins over STAGE's
STAGE_SETTINGS = (("--patience", "patience"), ("--hold-steps", "hold_steps"), ("--grace-steps", "grace_steps"),
                  ("--bc-weight", "bc_weight"), ("--seed", "seed"), ("--no-explore", "no_explore"),
                  ("--action-labels", "action_labels"))


def stage_flags(args) -> tuple[str, ...]:
    """The stage settings given (the corrector's rule, the BC weight, the seed, acting on the mean), not
    STAGE's; a switch (True) is its flag alone."""
    return tuple(word for flag, name in STAGE_SETTINGS if getattr(args, name) is not None
                 for word in ((flag,) if getattr(args, name) is True else (flag, str(getattr(args, name)))))


def stage_options(args) -> tuple[str, ...]:
    """STAGE's options less those given otherwise, then those given: each flag once."""
    given, kept, words = stage_flags(args), [], list(STAGE)
    while words:
        flag = words.pop(0)
        value = [words.pop(0)] if words and not words[0].startswith("--") else []
        if flag not in given:
            kept += [flag, *value]
    return tuple(kept) + given


def width_flags(args) -> tuple[str, ...]:
    """push_bound's own flags where given, not hil's: ``--stage-width W`` (the prior it trains)
    and ``--over-ros`` (where the stage runs)."""
    return (("--stage-width", str(args.stage_width)) if args.stage_width else ()) + \
        (("--over-ros",) if getattr(args, "over_ros", None) else ())


def online_key(variant: str, args) -> str:
    """The stage's entry: the variant, and the settings given where they are not the default."""
    flags = stage_flags(args) + width_flags(args)
    return variant + ("/" + "_".join(f.strip("-") for f in flags) if flags else "")


def stage(task_arg: str, variant: str, args) -> dict:
    """The online stage on the variant, in process (seed 0 unless ``--seed``), from its own auto
    prior on its own mixed log (200 episodes, 30 % expert, recorded with seed 0), with the anchor
    that carried pusher7_reach (STAGE)."""
    mix = args.work / f"{variant}-mix_s0_e0.3.db3"
    if not mix.exists():
        offline_rl("collect", "--task", task_arg, "--episodes", "200", "--expert-frac", "0.3", "--seed", "0",
                   "--out", str(mix))
    options, prior = stage_options(args), ()
    if args.stage_width:  # the stage fine-tunes its prior at the prior's width: an auto prior that wide
        seed = options[options.index("--seed") + 1]  # STAGE's, or the one given
        prior_dir = args.work / f"{variant}-auto-h{args.stage_width}-s{seed}"
        if not (prior_dir / "policy.pt").exists():
            offline_rl("train", "--algo", "auto", "--task", task_arg, "--bag", str(mix), "--hidden",
                       str(args.stage_width), "--seed", seed, "--out", str(prior_dir))
        prior = ("--prior", str(prior_dir / "policy.pt"))
    out = args.work / f"{online_key(variant, args).replace('/', '-')}-online-{args.online_steps}"
    done = out / "summary.json"
    config = json.loads(done.read_text())["config"] if done.exists() else {}
    over_ros = bool(getattr(args, "over_ros", None))
    if not (config.get("env_steps") == args.online_steps and config.get("from_topics", False) == over_ros and all(
            config.get(name) == getattr(args, name) for _, name in STAGE_SETTINGS
            if getattr(args, name) is not None)):
        # over ROS: the nodes as processes, the learner joining the arm's raw topics live
        where = "--from-topics" if over_ros else "--in-process"
        offline_rl("hil", "--online", where, "--task", task_arg, "--bag", str(mix),
                   "--env-steps", str(args.online_steps), "--eval-every", str(args.online_eval_every),
                   "--logger", "none", "--out", str(out), *options, *prior)  # a run already made is kept (resumes)
    summary = json.loads(done.read_text())
    curve = [{"env_steps": p["env_steps"], "success": p["success"], "intervention_rate": p["intervention_rate"]}
             for p in summary["curve"]]
    prior_metrics = Path(summary["prior"]).parent / "metrics.json"
    algorithm = json.loads(prior_metrics.read_text())["algorithm"] if prior_metrics.exists() else None
    return {"options": " ".join(options + width_flags(args)),
            "prior_algorithm": algorithm,
            "prior_success": summary["prior_success"], "best": max(p["success"] for p in curve),
            "final_success": summary["final_success"], "human_steps": summary["counts"]["human"], "curve": curve}


def dagger(task, width: int, args) -> dict:
    """Full DAgger on ``task`` at ``width`` (module docstring): the curve of success on the
    held-out resets against environment steps."""
    env = make_env(task)
    rows: dict[str, list] = {k: [] for k in ("obs", "action", "reward", "next_obs", "terminated", "truncated",
                                             "success", "episode", "step")}

    def episode(seed: int, policy) -> int:
        """One episode, the expert's action recorded at every state; ``policy`` (None: the
        expert) acts. Returns its steps."""
        obs, done, step = env.reset(seed), False, 0
        while not done:
            expert = expert_action(env)
            act = expert if policy is None else np.asarray(policy.act(obs[None]))[0]
            nxt, reward, done, info = env.step(act)
            terminated = bool(info.get("terminated", False))
            for k, v in (("obs", obs), ("action", expert), ("reward", reward), ("next_obs", nxt),
                         ("terminated", terminated), ("truncated", done and not terminated),
                         ("success", info["success"]), ("episode", seed), ("step", step)):
                rows[k].append(v)
            obs, step = nxt, step + 1
        return step

    def labelled() -> Transitions:
        arrays = {k: np.asarray(v, np.float32 if k in ("obs", "action", "reward", "next_obs") else
                                bool if k in ("terminated", "truncated", "success") else np.int64)
                  for k, v in rows.items()}
        return Transitions(**arrays, source=np.full(len(rows["obs"]), SOURCE_EXPERT, np.int64))

    episodes_per_round = max(1, args.dagger_round_steps // task.episodes.max_steps)
    cfg = TrainConfig(algo="bc", normalize_obs=True, hidden=width, deterministic=True, log_every=10**9)
    seed = iter(range(COLLECT_SEED, COLLECT_SEED + 10**6))
    env_steps = sum(episode(next(seed), None) for _ in range(args.dagger_demos))
    result = loop_train(labelled(), replace(cfg, steps=3 * args.dagger_steps), 0, task=task)
    held_out = range(HELD_OUT, HELD_OUT + args.eval_episodes)
    curve = [{"round": 0, "env_steps": env_steps,
              "success": round6(rollout_task(task, result.policy.act, held_out).successes / args.eval_episodes)}]
    print(f"  dagger h{width} round 0: {curve[-1]}", flush=True)
    for r in range(1, args.dagger + 1):
        env_steps += sum(episode(next(seed), result.policy) for _ in range(episodes_per_round))
        result = loop_train(labelled(), replace(cfg, steps=args.dagger_steps), 0, init=result.checkpoint, task=task)
        if r % 3 == 0 or r == args.dagger:
            success = rollout_task(task, result.policy.act, held_out).successes / args.eval_episodes
            curve.append({"round": r, "env_steps": env_steps, "success": round6(success)})
            print(f"  dagger h{width} round {r}: {curve[-1]}", flush=True)
    last = score_policy(result.policy, task, args.eval_episodes)  # how the last round's policy fails
    return {"task_digest": task.digest, "hidden": width, "demos": args.dagger_demos,
            "round_steps": args.dagger_round_steps, "episodes_per_round": episodes_per_round,
            "bc_steps_per_round": args.dagger_steps,
            "rounds": args.dagger, "labels": len(rows["obs"]), "curve": curve,
            "best": max(p["success"] for p in curve), "last_failures": last["failures"],
            "last_final_dist_m": last["final_dist_m"]}


def without_note(command: str) -> str:
    """The command that made the figures, without the page's note."""
    words, kept = shlex.split(command), []
    while words:
        word = words.pop(0)
        if word == "--note":
            words = words[1:]
        elif not word.startswith("--note="):
            kept.append(word)
    return shlex.join(kept)


def write(args, store: dict) -> None:
    """The JSON file, as it stands: after each cell, so a stopped run keeps what it measured."""
    if args.json:
        ordered = {**store, **{k: dict(sorted(store[k].items())) for k in ("variants", "cells", "dagger", "online")
                               if k in store}}
        write_text_atomic(args.json, json.dumps(ordered, indent=1) + "\n")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", nargs="+", default=["pusher_push", "direction"])
    parser.add_argument("--episodes", nargs="*", type=int, default=[100, 400],
                        help="expert episodes per log (none: no BC cells)")
    parser.add_argument("--widths", nargs="+", type=int, default=[256, 512], help="hidden widths")
    parser.add_argument("--steps", type=int, default=30000, help="BC gradient steps")
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--work", type=Path, default=Path("runs/push-bound"))
    parser.add_argument("--json", type=Path)
    parser.add_argument("--online-steps", type=int, default=0,
                        help="also run the online stage on each variant for this many environment steps (0: not)")
    parser.add_argument("--note", help="what the figures say, for the page (kept until another note replaces it)")
    parser.add_argument("--online-eval-every", type=int, default=2400, help="a multiple of every variant's episode")
    parser.add_argument("--patience", type=int, help="the stage's corrector: steps without progress before a "
                        "takeover (default: the stage's)")
    parser.add_argument("--hold-steps", type=int, help="the stage's corrector: steps of a takeover (default: the "
                        "stage's)")
    parser.add_argument("--grace-steps", type=int, help="the stage's corrector: states of an episode's start "
                        "before progress is judged (default: the stage's)")
    parser.add_argument("--bc-weight", type=float, help="the stage's actor: weight of its BC term (default: "
                        "STAGE's 100)")
    parser.add_argument("--seed", type=int, help="the stage's seed: its prior, learner and corrector (default: 0; "
                        "the mix is seed 0's)")
    parser.add_argument("--no-explore", action="store_true", default=None,
                        help="the stage's policy acts on its mean (hil --no-explore; default: it samples)")
    parser.add_argument("--action-labels", action="store_true", default=None,
                        help="the stage's corrector labels every state it leaves to the policy (hil "
                        "--action-labels; default: only its takeovers are imitated)")
    parser.add_argument("--over-ros", action="store_true", default=None,
                        help="the stage over ROS, the learner on the arm's raw topics (hil --online --from-topics; "
                        "default: in process)")
    parser.add_argument("--stage-width", type=int, help="the stage's networks: its prior trained this wide "
                        "(`offline-rl train --algo auto --hidden W`, seed 0 or --seed) and fine-tuned at that "
                        "width (default: the stage's own prior, 256)")
    parser.add_argument("--dagger", type=int, default=0, metavar="ROUNDS",
                        help="also run full DAgger for this many rounds per variant and width (0: not)")
    parser.add_argument("--dagger-demos", type=int, default=60, help="expert episodes before the first round "
                        "(default: the 30 %% expert share of the 200-episode mix)")
    parser.add_argument("--dagger-round-steps", type=int, default=3000,
                        help="environment steps the policy acts per round, in whole episodes")
    parser.add_argument("--dagger-steps", type=int, default=DAGGER_STEPS,
                        help="BC steps per round (three times this first)")
    args = parser.parse_args(argv)
    store = json.loads(args.json.read_text()) if args.json and args.json.exists() else {}
    add_run_facts(store)  # this command joins the file's; another CPU's figures are refused
    store["commands"] = list(dict.fromkeys(without_note(c) for c in store["commands"]))
    store.update(task="pusher_push", task_digest=load_task("pusher_push").digest, collect_seed=COLLECT_SEED,
                 reset_seeds=[HELD_OUT, HELD_OUT + args.eval_episodes - 1], near_within=NEAR)
    store.pop("command", None)
    if args.note:
        store["note"] = args.note
    variants, cells = store.setdefault("variants", {}), store.setdefault("cells", {})
    args.work.mkdir(parents=True, exist_ok=True)
    for variant in args.variants:
        task_arg = variant_task(variant, args.work)
        task = load_task(task_arg)
        expert = rollout_expert(task, range(HELD_OUT, HELD_OUT + args.eval_episodes))
        variants[variant] = {"task_digest": task.digest, "control_period_s": task.control_period,
                             "max_steps": task.episodes.max_steps, "obs_dim": task.obs_dim,
                             "expert_success": round6(expert.successes / args.eval_episodes)}
        for episodes in args.episodes:
            bag = args.work / f"{variant}-expert{episodes}.db3"
            if not bag.exists():
                offline_rl("collect", "--task", task_arg, "--episodes", str(episodes), "--expert-frac", "1",
                           "--seed", str(COLLECT_SEED), "--out", str(bag))
            for width in args.widths:
                key = f"{variant}/expert{episodes}/h{width}"
                kept = cells.get(key, {})
                if kept.get("task_digest") == task.digest and kept.get("bc_steps") == args.steps:
                    continue  # measured by an earlier run on the same task file: kept (--json merges)
                out = args.work / key.replace("/", "-")
                start = time.perf_counter()
                offline_rl("train", "--bag", str(bag), "--task", task_arg, "--algo", "bc", "--normalize-obs",
                           "--hidden", str(width), "--steps", str(args.steps), "--eval-episodes", "0",
                           "--out", str(out))
                cells[key] = {"variant": variant, "expert_episodes": episodes,
                              "transitions": episodes * task.episodes.max_steps, "hidden": width,
                              "bc_steps": args.steps, "train_wall_s": round(time.perf_counter() - start, 1),
                              **score(out / "policy.pt", task, args.eval_episodes)}
                print(key, json.dumps(cells[key]), flush=True)
                write(args, store)  # each cell as it is measured
        for width in args.widths if args.dagger else ():
            runs = store.setdefault("dagger", {})
            key = f"{variant}/h{width}" + ("" if args.dagger_steps == DAGGER_STEPS
                                           else f"/bc_steps_{args.dagger_steps}")
            kept = runs.get(key, {})
            settings = (args.dagger, args.dagger_demos, args.dagger_round_steps, args.dagger_steps)
            if kept.get("task_digest") != task.digest or settings != tuple(kept.get(k) for k in (
                    "rounds", "demos", "round_steps", "bc_steps_per_round")):
                start = time.perf_counter()
                runs[key] = {"variant": variant, **dagger(task, width, args),
                             "wall_s": round(time.perf_counter() - start, 1)}
                print(key, "dagger", json.dumps(runs[key]), flush=True)
                write(args, store)
        if args.online_steps:
            online, key = store.setdefault("online", {}), f"{online_key(variant, args)}/{args.online_steps}"
            kept = online.get(key, {})
            if kept.get("task_digest") != task.digest or kept.get("env_steps") != args.online_steps:
                online[key] = {"variant": variant, "task_digest": task.digest, "env_steps": args.online_steps,
                               **stage(task_arg, variant, args)}
                print(key, "online", json.dumps(online[key]), flush=True)
                write(args, store)
    write(args, store)
    return 0


if __name__ == "__main__":
    sys.exit(main())
