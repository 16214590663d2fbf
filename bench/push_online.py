"""The online stage on pusher_push, per seed, beside its ablations and a classifier's reward.

    python bench/push_online.py [--over-ros] [--seeds 0 1 2]
                                [--arms online classifier no_prior no_corrections offline_rounds]
                                [--env-steps 48000] [--eval-every 4800] [--out DIR]
                                [--json bench/pusher_push_online.json]

Every online arm is ``offline-rl hil --online --task pusher_push``, in one process
(``--in-process``) or, with ``--over-ros``, over ROS as a user runs it: the nodes as processes
on a private DDS domain, the learner joining the arm's raw topics live (``--from-topics``). Each
runs on the mixed log of its seed (200 episodes, 30 % expert: ``offline-rl collect --task
pusher_push --episodes 200 --expert-frac 0.3 --seed S``, the chapter's experiment's bags,
collected when absent), for the same environment steps (a whole number of 60-step episodes
near 50,000), from an ``--algo auto`` prior ``--width`` wide (default 512) that the script
trains on the seed's log, with the settings that carry the push task: the learner's ANCHOR
(pusher7_reach's: z-scored observations, the BC term of weight 100 also on the log's expert
episodes, the rates decaying over the budget, a quarter of each batch from the log) and the
corrector's RECIPE (a takeover at the first step without progress, kept to the episode's end,
and a label on every state it leaves to the policy, ``--action-labels``):

- ``online``: from that prior, with the scripted corrector, the simulator's reward;
- ``classifier``: the same, success judged by a success classifier (``offline-rl classifier
  train --labels simulator --successes 20 --failures 20 --head 16`` on the seed's log: 20
  labelled successes and 20 failures) instead of the simulator: the learner's reward and the
  episode's end (``--end-on-success``; over ROS the policy node labels the state the
  classifier judges a success and the sim ends the episode there). In process the simulator's
  word is counted beside it (``counts.false_ends``, ``counts.missed``);
- ``classifier_reward`` (when named): the classifier's reward alone, episodes ending at their
  time limit;
- ``no_prior``: the learner from scratch, at its default width (corrector and labels on);
- ``no_corrections``: the prior and online RL alone (no corrector, so no labels);
- ``offline_rounds``: the chapter's offline correction rounds instead of the online stage
  (``offline-rl hil --rounds R --episodes 100``, always over ROS: the policy node serves the
  prior, the scripted corrector takes over, AWAC is retrained from the served policy on the
  log and the corrections after each round), R rounds of 100 episodes within the same
  environment steps;
- ``no_anchor`` (when named in ``--arms``): the online arm without ANCHOR;
- ``critic_warmup`` (when named): the online arm with 5,000 steps of the critic alone on the
  log, the prior's actor fixed, before the first update (``--critic-warmup 5000``).

The curve: success without intervention of the deterministic policy on the task's 100
held-out resets every ``--eval-every`` steps, the intervention rate of each window, robot
time (steps x the control period). A 48,000-step session over raw topics takes an hour or more
on two cores. In one process the learner updates in step with the arm; over ROS it trains as
the messages arrive, so the two are not the same run. A run whose ``summary.json`` exists is
not run again (the script resumes; the priors, classifiers and offline rounds are shared by
both ways, in runs/push-online). Writes the JSON (each arm's summaries, the command, the machine), the plot
beside it, and prints the table of bench/RESULTS.md's section.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from hil_online import curve_of, run
from push_bound import ANCHOR  # the learner's anchor that carried pusher7_reach
from offline_rl_core.benchmarks.harness import run_facts
from offline_rl_core.common.atomic import write_json_atomic
from offline_rl_core.task.spec import load_task
from results_page import hil_table

TASK = "pusher_push"
ARMS = ("online", "classifier", "no_prior", "no_corrections", "offline_rounds")
# the corrector's settings that carry the push task (README, "Pushing a puck"): a
# takeover at the first step without progress, kept to the episode's end, and the corrector's
# labels of the states it leaves to the policy
RULE = ("--patience", "1", "--hold-steps", "60")  # the offline rounds' corrector too
RECIPE = RULE + ("--action-labels",)
ROUND_EPISODES = 100  # episodes per offline round (6,000 steps: 8 rounds in 48,000)
VARIANTS = ("critic_warmup", "no_anchor", "classifier_reward")  # run when named: the stage with one setting changed
BAGS = Path("runs/prior/pusher_push/bags")  # bench/prior_report.py --task pusher_push's logs
SHARED = Path("runs/push-online")  # the priors, the classifiers and the offline rounds, in process or over ROS


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--arms", nargs="+", choices=ARMS + VARIANTS, default=list(ARMS))
    p.add_argument("--env-steps", type=int, default=48_000, help="a multiple of the task's episodes")
    p.add_argument("--eval-every", type=int, default=4_800, help="a multiple of the task's episodes")
    p.add_argument("--width", type=int, default=512, help="the auto prior's width, fine-tuned at that width")
    p.add_argument("--eval-episodes", type=int, default=100)
    p.add_argument("--over-ros", action="store_true", help="every online arm over ROS, the learner joining the "
                   "arm's raw topics live (hil --online --from-topics); default: in one process")
    p.add_argument("--out", help="run folder (default: runs/push-online, runs/push-online-ros with --over-ros)")
    p.add_argument("--json", default="bench/pusher_push_online.json")
    p.add_argument("--note", help="what bounded the measurement (seeds, arms not run), for the page")
    p.add_argument("--collect", action="store_true", help="run nothing: write the JSON and the plot from the named "
                   "seeds' and arms' runs that exist (arms run as separate invocations, side by side)")
    args = p.parse_args()
    facts = run_facts()
    offline_rl = [sys.executable, "-m", "offline_rl_core"]
    out = Path(args.out or ("runs/push-online-ros" if args.over_ros else "runs/push-online"))
    results: dict = {}
    for seed in args.seeds:
        bag = BAGS / f"mix_s{seed}_e0.3.db3"
        if not bag.exists() and not args.collect:
            bag.parent.mkdir(parents=True, exist_ok=True)
            subprocess.run([*offline_rl, "collect", "--task", TASK, "--episodes", "200", "--expert-frac", "0.3",
                            "--seed", str(seed), "--out", str(bag)], check=True)
        prior = SHARED / "priors" / f"auto-h{args.width}-s{seed}" / "policy.pt"
        if not prior.exists() and not args.collect:
            subprocess.run([*offline_rl, "train", "--algo", "auto", "--task", TASK, "--bag", str(bag), "--hidden",
                            str(args.width), "--seed", str(seed), "--out", str(prior.parent)], check=True)
        for arm in args.arms:
            run_dir = (SHARED if arm == "offline_rounds" else out) / arm / f"seed{seed}"
            if args.collect and not (run_dir / "summary.json").exists():
                continue
            if arm == "offline_rounds":
                rounds = args.env_steps // (ROUND_EPISODES * load_task(TASK).episodes.max_steps)
                cmd = [*offline_rl, "hil", "--rounds", str(rounds), "--episodes", str(ROUND_EPISODES), "--task", TASK,
                       "--bag", str(bag), "--prior", str(prior), "--seed", str(seed), *RULE,
                       "--eval-episodes", str(args.eval_episodes), "--out", str(run_dir)]
                results.setdefault(arm, {})[str(seed)] = run(cmd, run_dir / "summary.json")
                continue
            where = "--from-topics" if args.over_ros else "--in-process"
            cmd = [*offline_rl, "hil", "--online", where, "--task", TASK, "--bag", str(bag),
                   "--seed", str(seed), "--env-steps", str(args.env_steps), "--eval-every", str(args.eval_every),
                   "--eval-episodes", str(args.eval_episodes), "--logger", "none", "--out", str(run_dir)]
            cmd += ["--prior", str(prior)] if arm != "no_prior" else ["--no-prior"]
            anchor = [] if arm == "no_anchor" else list(ANCHOR)
            cmd += [*anchor, *RECIPE] if arm != "no_corrections" else [*anchor, "--corrector", "none"]
            if arm in ("classifier", "classifier_reward"):
                classifier = SHARED / "classifiers" / f"seed{seed}.pt"
                if not classifier.exists():
                    subprocess.run([*offline_rl, "classifier", "train", "--bag", str(bag), "--labels", "simulator",
                                    "--successes", "20", "--failures", "20", "--head", "16", "--seed", str(seed),
                                    "--out", str(classifier)], check=True)
                cmd += ["--success", str(classifier)] + (["--end-on-success"] if arm == "classifier" else [])
            cmd += {"critic_warmup": ["--critic-warmup", "5000"]}.get(arm, [])
            results.setdefault(arm, {})[str(seed)] = run(cmd, run_dir / "summary.json")
            task = load_task(TASK)
            write_json_atomic(args.json, {"task": task.name, "task_digest": task.digest, "arms": results,
                                          **({"note": args.note} if args.note else {}), **facts,
                                          "command": command_line(sys.argv[1:])})
    print(hil_table(results))
    plot(results, Path(args.json).with_suffix(".png"))
    return 0


def command_line(argv: list[str]) -> str:
    """The command that made the figures (without the page's note)."""
    kept, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg == "--note":
            skip = True
        elif not arg.startswith("--note="):
            kept.append(arg)
    return " ".join(["python bench/push_online.py", *kept])


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    period = load_task(TASK).control_period
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for j, (arm, by_seed) in enumerate(results.items()):
        for i, (seed, summary) in enumerate(sorted(by_seed.items(), key=lambda kv: int(kv[0]))):
            steps, success = curve_of(arm, summary, load_task(TASK).episodes.max_steps)
            label = f"{arm}, seed {seed}"
            style = dict(color=f"C{j}", alpha=1.0 - 0.25 * i, lw=2)
            axes[0].plot(steps, success, "o-", label=label, **style)
            if arm not in ("no_corrections", "offline_rounds"):  # rounds: no curve of windows
                axes[1].plot([s * period / 60 for s in steps], [p["intervention_rate"] for p in summary["curve"]],
                             "s--", label=label, **style)
    axes[0].axhline(0.9, color="grey", ls=":", lw=1)
    axes[0].set_xlabel("environment steps")
    axes[0].set_ylabel("success without intervention (100 held-out resets)")
    axes[1].set_xlabel(f"robot time, min ({1 / period:g} Hz)")
    axes[1].set_ylabel("intervention rate (window)")
    for ax in axes:
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    fig.suptitle(f"{TASK}: the online stage (auto prior, scripted corrector) and its ablations", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
