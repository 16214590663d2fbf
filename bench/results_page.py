"""bench/RESULTS.md, generated from the JSON files in bench/: the current figures, each with
the command that measured it and the machine it ran on.

    python bench/results_page.py           # rewrite bench/RESULTS.md (the last step of `make bench`)
    python bench/results_page.py --check   # exit 1 when bench/RESULTS.md is not what the JSON gives

`offline-rl bench` files are merged per configuration (CPU model and flags, kernel caps,
device, quick or full): for each figure the newest measurement is shown, so a partial run
(`--only train`) replaces only its own figures. Every other JSON file has a section of its
own below; a JSON file that no section renders is an error, so nothing measured is left off.
The table renderers here are also what the bench scripts print.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # `python bench/results_page.py` from any Python, no install needed
    sys.path.insert(0, str(ROOT))

from offline_rl_core.common.atomic import write_text_atomic  # noqa: E402  (both pure Python: no torch)
from offline_rl_core.evaluation.stats import newcombe_diff_ci, wilson_ci  # noqa: E402

BENCH = ROOT / "bench"
PAGE = BENCH / "RESULTS.md"
GROUP_ORDER = ("train", "decode", "eval", "serve", "record", "online")  # as `offline-rl bench` runs them
FACT_KEYS = ("command", "commands", "machine", "measured_at", "provenance")


# ----------------------------------------------------------------------------- provenance

def commands_of(payload: dict) -> list[str]:
    if payload.get("command"):
        return [payload["command"]]
    return list(payload.get("commands") or [])


def machine_text(m: dict) -> str:
    """CPU model, cores and instruction-set flags (and caps, GPU), from whichever keys the
    writer of the time recorded."""
    model = m.get("cpu_model") or m.get("cpu") or "CPU model not recorded"
    cores = f", {m['cpu_count']} cores" if m.get("cpu_count") else ""
    flags = m.get("cpu_isa_flags") or m.get("isa_flags") or m.get("isa") or m.get("cpu_flags")
    if flags:
        flag_text = "flags " + " ".join(flags)
    elif m.get("bf16_flags"):
        flag_text = "flags " + " ".join(m["bf16_flags"]) + " (only its bf16 flags were recorded)"
    else:
        flag_text = "flags not recorded"
    text = f"{model}{cores}, {flag_text}"
    if m.get("kernel_isa_limits"):
        text += "; kernels capped at " + " ".join(f"{k}={v}" for k, v in sorted(m["kernel_isa_limits"].items()))
    if m.get("cuda_available") and m.get("gpu"):
        text += f"; GPU {m['gpu']}"
    return text


def software_text(m: dict) -> str:
    parts = [f"torch {m['torch']}" if m.get("torch") else "", f"Python {m['python']}" if m.get("python") else ""]
    default = (m.get("kernels") or {}).get("default") or {}
    if default.get("dtype"):
        parts.append(f"hidden layer in {default['dtype']} by default")
    if m.get("threads_choice"):
        parts.append(f"threads: {m['threads_choice']}")
    if m.get("loadavg_start"):
        parts.append(f"load {m['loadavg_start'][0]} at the start")
    return ", ".join(p for p in parts if p)


def when(payload: dict) -> str:
    at = payload.get("measured_at")  # ISO 8601, UTC
    return f"{at[:10]} {at[11:16]} UTC" if at else "time not recorded"


def machine_of(payload: dict) -> dict:
    """The machine a file records: its ``machine`` object, or the CPU facts at its top level
    (``cpu``, ``cpu_flags``, ``cores``), as the bench scripts of one measurement write them."""
    if payload.get("machine"):
        return payload["machine"]
    return {"cpu_model": payload.get("cpu"), "cpu_flags": payload.get("cpu_flags"), "cpu_count": payload.get("cores")}


def note_lines(payload: dict) -> list[str]:
    """A section's note (what bounded its measurement), as a paragraph, or nothing."""
    return [str(payload["note"]), ""] if payload.get("note") else []


def source_lines(name: str, payload: dict) -> list[str]:
    m = machine_of(payload)
    lines = [f"- [{name}]({name}), {when(payload)}: " + "; ".join(f"`{c}`" for c in commands_of(payload))]
    lines.append(f"  - {machine_text(m)}" + (f" ({software_text(m)})" if software_text(m) else ""))
    if m.get("note"):
        lines.append(f"  - machine: {m['note']}")
    if payload.get("provenance"):
        lines.append(f"  - {payload['provenance']}")
    return lines


def missing_facts(payload: dict) -> list[str]:
    """What a JSON file under bench/ fails to say about its figures (tests/test_results_page.py)."""
    missing = []
    runs = payload.get("runs") if isinstance(payload.get("runs"), dict) else None
    for part in ([payload] if runs is None else [payload, *runs.values()]):
        if not commands_of(part):
            missing.append("command")
        m = machine_of(part)
        if not (m.get("cpu_model") or m.get("cpu")):
            missing.append("machine")
        if runs is not None:  # a file of several runs: each run says its own
            break
    if runs is not None:
        for run_name, run in runs.items():
            if not commands_of(run):
                missing.append(f"runs.{run_name}.command")
            if not ((run.get("machine") or {}).get("cpu_model")):
                missing.append(f"runs.{run_name}.machine")
    return missing


# ----------------------------------------------------------------------------- offline-rl bench files

def is_bench_run(payload: dict) -> bool:
    return "settings" in payload or isinstance(payload.get("runs"), dict)


def bench_runs(name: str, payload: dict) -> list[tuple[str, dict]]:
    """(label, payload) of each `offline-rl bench` run in a file: the file itself, or its ``runs``."""
    if isinstance(payload.get("runs"), dict):
        return [(f"{name}, run {run_name}", run) for run_name, run in payload["runs"].items()]
    return [(name, payload)]


def configuration(run: dict) -> tuple:
    m = run.get("machine") or {}
    flags = m.get("cpu_isa_flags") or m.get("isa_flags") or m.get("bf16_flags") or []
    settings = run.get("settings") or {}
    return (m.get("cpu_model", ""), m.get("cpu_count"), tuple(flags), tuple(sorted((m.get("kernel_isa_limits") or {}).items())),
            settings.get("device", "cpu"), bool(settings.get("quick")), run.get("variant", ""))


def configuration_title(run: dict) -> str:
    m, settings = run.get("machine") or {}, run.get("settings") or {}
    title = machine_text(m)
    if settings.get("device", "cpu") != "cpu":
        title = f"training on {settings['device']}; host {title}"
    if settings.get("quick"):
        title += " — `--quick`"
    if run.get("variant"):
        title += f" — {run['variant']}"
    return title


def number(x: float | None, unit: str) -> str:
    if x is None:
        return "-"
    if unit in ("ms", "s") or abs(x) < 10:
        return f"{x:.3g}" if abs(x) < 1000 else f"{x:,.0f}"
    return f"{x:,.0f}"


def cell(text: str) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def bench_sections(files: dict[str, dict]) -> tuple[list[str], list[str]]:
    """The markdown of the `offline-rl bench` figures, one section per configuration, and the
    files none of whose figures is current."""
    runs = []  # (sort key, label, file, run)
    for order, (name, payload) in enumerate(files.items()):
        for k, (label, run) in enumerate(bench_runs(name, payload)):
            runs.append(((run.get("measured_at") or payload.get("measured_at") or "", order, k), label, name, run))
    runs.sort(key=lambda r: r[0])
    current: dict[tuple, dict[tuple[str, str], tuple[str, dict]]] = {}
    titles: dict[tuple, str] = {}
    for _, label, _, run in runs:  # oldest first: a newer run's figure replaces an older one's
        cfg = configuration(run)
        titles[cfg] = configuration_title(run)
        for group in GROUP_ORDER:
            for fig_name, fig in (run.get(group) or {}).items():
                current.setdefault(cfg, {})[(group, fig_name)] = (label, fig)
    shown = {label for figs in current.values() for label, _ in figs.values()}
    newest = {cfg: max(key for key, _, _, run in runs if configuration(run) == cfg) for cfg in current}
    out = ["## Speed (`offline-rl bench`)", "",
           "`offline-rl bench` files merged per configuration: for each figure, the newest measurement on that "
           "CPU (and kernel caps, device, run length); the configuration measured last comes first.", ""]
    for cfg in sorted(current, key=lambda c: newest[c], reverse=True):
        figs = current[cfg]
        out += [f"### {titles[cfg]}", ""]
        labels = [label for _, label, _, run in runs if label in {lb for lb, _ in figs.values()}]
        by_label = {label: (name, run) for _, label, name, run in runs}
        out.append("Measured by:")
        for label in sorted(set(labels), key=labels.index):
            name, run = by_label[label]
            src = source_lines(label, run)
            src[0] = src[0].replace(f"[{label}]({label})", f"[{label}]({name})")
            out += src
        out += ["", "| group | figure | ours | reference | ratio | target | met | measured by | note |",
                "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        for group in GROUP_ORDER:
            for (g, fig_name), (label, fig) in sorted(figs.items()):
                if g != group:
                    continue
                unit = fig.get("unit", "")
                met = {True: "yes", False: "NO", None: "-"}[fig.get("met")] if fig.get("status", "ok") == "ok" \
                    else fig["status"]
                ratio = "-" if fig.get("ratio") is None else f"{fig['ratio']:.2f}x"
                ours = "-" if fig.get("ours") is None else f"{number(fig['ours'], unit)} {unit}"
                ref = "-" if fig.get("reference") is None else f"{number(fig['reference'], unit)} {unit}"
                out.append(f"| {group} | `{fig_name}` | {ours} | {ref} ({cell(fig.get('reference_name', ''))}) | {ratio} "
                           f"| {cell(fig.get('target_text', ''))} | {met} | {label} | {cell(fig.get('note', ''))} |")
        out.append("")
    not_current = [name for name, payload in files.items()
                   if not any(label in shown for label, _ in bench_runs(name, payload))]
    return out, not_current


# ----------------------------------------------------------------------------- the chapter's experiment

# The seed chapter's reported numbers (shared/pusher_reach.md): fixed facts, printed beside ours.
CHAPTER_MIX = {"BC": ("0.03 / 0.07 / 0.05", "0.154 / 0.147 / 0.144"), "AWAC": ("0.27 / 0.20 / 0.21", "0.109 / 0.100 / 0.089")}
CHAPTER_EXPERT = {"BC": "about 0.2", "AWAC": "0.27 / 0.37 / 0.38", "AWAC |Q|": "about 1.08",
                  "naive |Q|": "7.29 / 7.41 / 6.74", "naive": "collapses toward random"}


def per_seed(values) -> str:
    return " / ".join(values)


def chapter_section(name: str, payload: dict) -> list[str]:
    arms = payload["arms"]

    def seeds(arm):
        return [m for _, m in sorted(arms[arm]["seeds"].items(), key=lambda kv: int(kv[0]))] if arm in arms else []

    def rates(ms, key):
        return per_seed(f"{m[key]:.2f}" for m in ms)

    def dists(ms, key):
        return per_seed(f"{m[key]:.3f}" for m in ms)

    first = next(iter(next(iter(arms.values()))["seeds"].values()))
    out = ["## The chapter's experiment", "",
           f"`offline-rl experiment --seeds 0 1 2`: per seed, the chapter's dataset ({first['episodes']} episodes), BC "
           f"and the offline learner ({first['steps']} steps each), {first['n_pooled']} pooled held-out rollouts each; "
           "the chapter's reported numbers beside ours.", ""]
    out += source_lines(name, payload) + [""]
    mix = seeds("mix_awac")
    if mix:
        out += ["Mixed data (200 episodes, 30 % expert):", "",
                "| learner | success, seeds 0 / 1 / 2 | chapter | final distance m | chapter | command |",
                "| --- | --- | --- | --- | --- | --- |",
                f"| BC | {rates(mix, 'bc_success_rate')} | {CHAPTER_MIX['BC'][0]} | {dists(mix, 'bc_mean_final_dist')} "
                f"| {CHAPTER_MIX['BC'][1]} | `{arms['mix_awac']['command']}` |"]
        for arm, label in (("mix_awac", "AWAC"), ("mix_iql", "IQL"), ("mix_filtered_bc", "filtered BC (top 10 %)")):
            ms = seeds(arm)
            if ms:
                ref = CHAPTER_MIX.get(label, ("-", "-"))
                out.append(f"| {label} | {rates(ms, 'offline_success_rate')} | {ref[0]} "
                           f"| {dists(ms, 'offline_mean_final_dist')} | {ref[1]} | `{arms[arm]['command']}` |")
        out += ["", "The offline learner minus BC, Newcombe 95 % interval (the chapter, seed 0: +0.15..+0.34; "
                "it excludes 0 on every seed there):", "",
                "| learner | seed 0 | seed 1 | seed 2 | pooled | pooled success [Wilson 95 %] |",
                "| --- | --- | --- | --- | --- | --- |"]
        for arm, label in (("mix_awac", "AWAC"), ("mix_iql", "IQL"), ("mix_filtered_bc", "filtered BC")):
            ms = seeds(arm)
            if ms:
                n = sum(m["n_pooled"] for m in ms)
                k_off = sum(round(m["offline_success_rate"] * m["n_pooled"]) for m in ms)
                k_bc = sum(round(m["bc_success_rate"] * m["n_pooled"]) for m in ms)
                lo, hi = newcombe_diff_ci(k_off, n, k_bc, n)
                wlo, whi = wilson_ci(k_off, n)
                diffs = [f"{m['diff_ci_lo']:+.2f}..{m['diff_ci_hi']:+.2f}" for m in ms]
                out.append(f"| {label} | " + " | ".join(diffs) + f" | {lo:+.2f}..{hi:+.2f} "
                           f"| {k_off}/{n} = {k_off / n:.3f} [{wlo:.3f}, {whi:.3f}] |")
        out.append("")
    expert, naive = seeds("expert_awac"), seeds("expert_naive")
    if expert or naive:
        out += ["Expert-only data (`--expert-frac 1.0`) and the Break-It (naive max-Q):", "",
                "| | seeds 0 / 1 / 2 | chapter |", "| --- | --- | --- |"]
        if expert:
            out += [f"| BC success; final distance m | {rates(expert, 'bc_success_rate')}; "
                    f"{dists(expert, 'bc_mean_final_dist')} | {CHAPTER_EXPERT['BC']} |",
                    f"| AWAC success; final distance m | {rates(expert, 'offline_success_rate')}; "
                    f"{dists(expert, 'offline_mean_final_dist')} | {CHAPTER_EXPERT['AWAC']} |",
                    f"| AWAC critic, mean \\|Q\\| on the data | {rates(expert, 'offline_mean_abs_q')} "
                    f"| {CHAPTER_EXPERT['AWAC |Q|']} |",
                    "| AWAC − BC, Newcombe 95 % | " + per_seed(f"{m['diff_ci_lo']:+.2f}..{m['diff_ci_hi']:+.2f}"
                                                       for m in expert) + " | not seed-robust |"]
        if naive:
            out += [f"| naive max-Q critic, mean \\|Q\\| | {rates(naive, 'offline_mean_abs_q')} | {CHAPTER_EXPERT['naive |Q|']} |",
                    f"| naive success; final distance m | {rates(naive, 'offline_success_rate')}; "
                    f"{dists(naive, 'offline_mean_final_dist')} (random: 0.176) | {CHAPTER_EXPERT['naive']} |"]
        out += [""] + [f"- `{arms[arm]['command']}`" for arm in ("expert_awac", "expert_naive") if arm in arms] + [""]
    return out


# ----------------------------------------------------------------------------- crash safety

def crash_table(trials: list[dict]) -> str:
    """One row per (recorder mode, fault, storage) over its kill moments (bench/crash_safety.py prints it too)."""
    lines = ["| recorder | fault | storage | kills | received (mean) | opens as left, no repair | rosbags opens as left "
             "| needed `bag repair` | recovered (mean) | lost, worst kill (as time at the rate received) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    groups: dict[tuple, list[dict]] = {}
    for r in trials:
        groups.setdefault((r["mode"], r["fault"], r["storage"]), []).append(r)
    for (mode, fault, storage), rs in groups.items():
        n = len(rs)
        received = sum(r["received"] for r in rs) / n
        recovered = sum(r["repaired"] or 0 for r in rs) / n
        opened = sum(r["read"] is not None for r in rs)
        opens = sum(bool(r["rosbags_opens"]) for r in rs)
        repaired = sum(bool(r["repair_steps"]) for r in rs)
        lost = max(r["lost"] for r in rs)
        lost_s = max(r["lost"] / r["rate_per_s"] if r["rate_per_s"] else 0 for r in rs)
        lines.append(f"| {mode} | {fault} | {storage} | {n} | {received:.0f} | {opened}/{n} | {opens}/{n} "
                     f"| {repaired}/{n} | {recovered:.0f} | {lost} ({lost_s:.2f} s) |")
    return "\n".join(lines)


def crash_section(name: str, payload: dict) -> list[str]:
    trials = payload["trials"]
    prefix = [r.get("gap_free_prefix", r.get("rows_in_order")) for r in trials]
    return ["## Crash safety of recording", "",
            "Sim and recorder nodes over DDS; the recorder gets the signal at each kill moment after it starts "
            "recording; a probe subscriber counts what the sim published before the signal. `active`: lockstep sim "
            "driven by the recorder; `passive`: realtime sim at 50 Hz, `recorder --passive`. Lost: transitions "
            "published before the signal that the bag lacks.", ""] + source_lines(name, payload) + [
        "", crash_table(trials), "",
        f"What the bag kept was a gap-free prefix of what was published in {sum(bool(p) for p in prefix)} of "
        f"{len(trials)} trials.", ""]


# ----------------------------------------------------------------------------- the HIL-SERL stage

THRESHOLDS = ("0.5", "0.8", "0.9", "0.95")
ARM_ORDER = ("online", "no_anchor", "imitate_expert", "critic_warmup", "normalize_obs", "classifier", "classifier_reward", "no_prior", "no_corrections", "offline_rounds")  # the stage, then its variants


def hil_table(arms: dict) -> str:
    """The online stage and its ablations, one row per arm and seed (bench/hil_online.py prints it too)."""
    rows = ["| arm | seed | prior's success | success at the end [95 % Wilson] | env steps to 0.5 / 0.8 / 0.9 / 0.95 "
            "| learner wall s to 0.95 | intervention rate | where |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    order = {arm: i for i, arm in enumerate(ARM_ORDER)}
    for arm, by_seed in sorted(arms.items(), key=lambda kv: order.get(kv[0], len(order))):
        for seed, s in sorted(by_seed.items(), key=lambda kv: int(kv[0])):
            lo, hi = s["final_ci"]
            if arm == "offline_rounds":
                rows.append(f"| {arm} ({len(s['rounds'])} rounds x {s['rounds'][0]['episodes']} episodes) | {seed} "
                            f"| {s['prior_success']:.2f} | {s['final_success']:.2f} [{lo:.2f}, {hi:.2f}] | (end only) | - "
                            f"| {s['intervention_rate_last']:.3f} (last round) | over ROS |")
                continue
            to = " / ".join(str(s["to"][t]["env_steps"]) if s["to"].get(t) else "-" for t in THRESHOLDS)
            wall = f"{s['to']['0.95']['wall_s']:.0f}" if s["to"].get("0.95") else "-"
            rows.append(f"| {arm} | {seed} | {s['prior_success']:.2f} | {s['final_success']:.2f} [{lo:.2f}, {hi:.2f}] "
                        f"| {to} | {wall} | {s['intervention_rate']:.3f} | {s['where']} |")
    return "\n".join(rows)


def hil_section(name: str, payload: dict) -> list[str]:
    return ["## The HIL-SERL stage", "",
            "Each run from the 8000-step AWAC prior of its seed on `bags/mix.db3` (none for `no_prior`), lockstep, "
            "scripted corrector (none for `no_corrections`); success without intervention of the deterministic policy "
            "on the chapter's 100 held-out resets along the run. `offline_rounds`: `offline-rl hil`, AWAC retrained "
            "between rounds of corrected episodes, with the same budget of environment steps.", ""] + \
        source_lines(name, payload) + ["", hil_table(payload["arms"]), "", "![success against environment steps](hil_online.png)", ""]


def multi_actor_table(arms: list[dict]) -> str:
    """Several actors, one learner: one row per number of actors (bench/multi_actor.py prints it too)."""
    rows = ["| actors | success at the end [95 % Wilson] | env steps to the threshold | learner wall s to it "
            "| updates by then | session wall s | updates in all | learner busy training | load average (mean / max) |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for a in arms:
        f, r, load = a["final"], a["reached"], a.get("load") or {}
        reached = (f"{r['env_steps']} | {r['wall_s']:.0f} | {r['updates']}" if r else
                   f"not reached ({a['threshold']:g}) | - | -")
        rows.append(f"| {a['actors']} | {f['success']:.2f} [{f['ci'][0]:.2f}, {f['ci'][1]:.2f}] | {reached} "
                    f"| {a['session_wall_s']:.0f} | {f['updates']} | {a['learner_train_s'] / a['learner_wall_s']:.0%} | "
                    f"{load.get('mean', '-')} / {load.get('max', '-')} |")
    return "\n".join(rows)


def multi_actor_section(name: str, payload: dict) -> list[str]:
    st = payload["settings"]
    return ["## Several actors, one learner", "",
            f"`offline-rl hil --online --actors N --no-prior` on {st['task']}, {st['mode']}, {st['corrector']} "
            f"corrector, the learner from scratch, {st['env_steps']} environment steps in all over the actors; "
            f"success without intervention on {st['eval_episodes']} held-out resets every {st['eval_every']} steps; "
            f"threshold {st['threshold']:g}. Wall times are the learner's, on this machine's cores shared by every "
            "node of every actor (and by whatever else ran, see the load).", ""] + \
        source_lines(name, payload) + ([str(payload["note"]), ""] if payload.get("note") else [""]) + \
        [multi_actor_table(payload["arms"]), ""]


def pusher7_online_section(name: str, payload: dict) -> list[str]:
    lines = ["## The HIL-SERL stage on pusher7_reach", "",
             f"The online stage on the 7-joint arm (task `{payload['task']}`, digest `{payload['task_digest']}`), "
             "lockstep, scripted corrector, from the `--algo auto` prior of its seed on the task's 200-episode mix "
             "(30 % expert); success without intervention of the deterministic policy on the task's held-out resets "
             "along the run. `online_raw_topics`: over ROS, the learner joining the arm's raw topics live "
             "(`--from-topics`); `online_in_process`: the same stage in one process; a suffix names an option the "
             "arm changed (`_normalize_obs`: `--normalize-obs`, actor and critic on z-scored observations; "
             "`_imitate_expert`: `--imitate-expert`, the BC term also on the mix's expert episodes; `_bc30`: "
             "`--bc-weight 30`; `_lr_decay`: `--lr-decay`, the learning rates along a cosine to zero over the budget; "
             "`_offline0.25`: `--offline-ratio 0.25`, a quarter of each batch from the mix; "
             "`_noise0.2`: `--corrector-noise 0.2`, noise of std 0.2 on the corrector's actions; "
             "`_stick`: `--steer stick`, the corrector steering the fingertip straight at the goal; "
             "`@DIGEST`: the arm as measured on an earlier version of the task file, digest DIGEST, before its "
             "observation gained `direction: [goal, fingertip]`). Over raw "
             "topics an episode's last step makes no transition, so 200 episodes train on 19,800 steps of the 20,000: "
             "the curve's last point is the learner's final weights.", ""]
    lines += note_lines(payload)
    return lines + source_lines(name, payload) + ["", hil_table(payload["arms"]), "",
                                                  "![success against environment steps](pusher7_online.png)", ""]


def probes_table(data: dict) -> str:
    lines = ["| variant | what it changes | success at 10k / 15k / 17.5k / 20k steps | best point | steps to 0.8 / 0.9 "
             "| intervention rate, last window | final policy's failures: within 0.1 m, closest (median) |",
             "|---|---|---|---|---|---|---|"]
    for name, rec in data["variants"].items():
        at = {p["env_steps"]: p for p in rec["curve"]}
        points = " / ".join(f"{at[n]['success']:.2f}" if n in at else "-" for n in (10000, 15000, 17500, 20000))
        best = max(rec["curve"], key=lambda p: p["success"])
        reach = " / ".join(next((str(p["env_steps"]) for p in rec["curve"] if p["success"] >= t), "-")
                           for t in (0.8, 0.9))
        lines.append(f"| {name} | {rec['changes']} | {points} | {best['success']:.2f} [{best['ci'][0]:.2f}, "
                     f"{best['ci'][1]:.2f}] at {best['env_steps']} | {reach} | {rec['curve'][-1]['intervention_rate']:.3f} | "
                     + (f"{f['within_0.1m']} of {f['count']}, {f['closest_median']:.3f} m |" if (f := rec.get("failures"))
                        else "- |"))
    return "\n".join(lines)


def task_curves_table(curves: dict, expert_frac: float) -> str:
    """Every learner at the whole budget on another task (prior_report.py --task): per seed and
    pooled with Wilson intervals, and each against BC (Newcombe)."""
    by_label: dict[str, list] = {}
    for rec in curves.values():
        if rec["points"] and rec["expert_frac"] == expert_frac:
            by_label.setdefault(rec["label"], []).append(rec)
    rows = [(label, [r["points"][-1] for r in sorted(recs, key=lambda r: r["seed"])])
            for label, recs in by_label.items()]  # the whole budget, per seed
    pooled = {label: (sum(p["successes"] for p in pts), sum(p["episodes"] for p in pts)) for label, pts in rows}
    lines = ["| learner | steps in the budget, seeds | success | pooled [95 % CI] | minus BC [95 % CI, Newcombe] "
             "| final distance m |", "|---|---|---|---|---|---|"]
    for label, pts in rows:
        s, n = pooled[label]
        a, b = wilson_ci(s, n)
        steps = " / ".join(str(p["steps"]) for p in pts)
        success = " / ".join(f"{p['success_rate']:.2f}" for p in pts)
        dist = " / ".join(f"{p['mean_final_dist']:.3f}" for p in pts)
        diff = "-"
        if "BC" in pooled and label != "BC":
            lo, hi = newcombe_diff_ci(s, n, *pooled["BC"])
            diff = f"{s / n - pooled['BC'][0] / pooled['BC'][1]:+.3f} [{lo:+.3f}, {hi:+.3f}]"
        lines.append(f"| {label} | {steps} | {success} | {s / n:.3f} [{a:.3f}, {b:.3f}] | {diff} | {dist} |")
    return "\n".join(lines)


def push_experiment_section(name: str, payload: dict) -> list[str]:
    curves = payload.get("curves", {})
    budget = next(iter(curves.values()))["budget_s"] if curves else None
    return ["## The chapter's experiment on pusher_push", "",
            f"Every learner for the same training time ({budget:.1f} s: the chapter's 8000-step AWAC loop on this "
            "machine, each learner's steps from its own measured step rate) on the push task's mixed log of each "
            "seed (`offline-rl collect --task pusher_push --episodes 200 --expert-frac 0.3 --seed S`, S = 0, 1, 2; "
            "recorded over ROS on raw topics it gives the same rows, `tests/test_ros_recorder.py`), 100 held-out "
            "rollouts per seed (reset seeds 500000 + S ..). `--algo auto` plans from the data alone (it looks at no "
            "reset). The success against training time: [pusher_push_curves.png](pusher_push_curves.png).", ""] \
        + source_lines(name, payload) + ["", task_curves_table(curves, 0.3), "",
                                         "![success against training time](pusher_push_curves.png)", ""]


def push_online_section(name: str, payload: dict) -> list[str]:
    """The online stage on pusher_push beside its ablations and the classifier's reward (bench/push_online.py)."""
    lines = ["## The HIL-SERL stage on pusher_push", "",
             f"The online stage on the push task (digest `{payload['task_digest']}`), lockstep, from the `--algo "
             "auto` prior of each seed's mixed log (200 episodes, 30 % expert) trained 512 wide, the scripted "
             "corrector taking over at the first step without progress and keeping the arm to the episode's end "
             "(`--patience 1 --hold-steps 60`) and labelling every state it leaves to the policy "
             "(`--action-labels`), the same environment-step budget for every arm; success without intervention of "
             "the deterministic policy on the task's 100 held-out resets along the run. Each arm runs in one "
             "process, or over ROS with the learner joining the arm's raw topics live (`--over-ros`, "
             "`--from-topics`): the table's last column. `online`: the stage; `no_anchor`: without the learner's "
             "anchor (`--normalize-obs --imitate-expert --bc-weight 100 --lr-decay --offline-ratio 0.25`); "
             "`classifier`: success judged by a success classifier trained on 20 labelled successes and 20 "
             "failures of the seed's log (`--head 16`) instead of the simulator, for the learner's reward and the "
             "episode's end (`--end-on-success`: over ROS the policy node labels the state it judges a success and "
             "the sim ends the episode there); `classifier_reward`: its reward alone, episodes ending at their "
             "time limit; `no_prior`: from "
             "scratch at the learner's default width; `no_corrections`: no corrector (so no labels); "
             "`offline_rounds`: the offline correction rounds over ROS (`offline-rl hil --rounds`, AWAC retrained "
             "from the served policy on the log and the corrections after each round of 100 episodes) within the "
             "same steps. Curves of success and of the intervention rate against environment steps and robot time: "
             "[pusher_push_online.png](pusher_push_online.png).", ""]
    lines += note_lines(payload)
    lines += source_lines(name, payload) + ["", hil_table(payload["arms"]), ""]
    # in process the classifier ends episodes and the run counts them; over ROS the note says what it judged
    judged = {seed: s for seed, s in payload["arms"].get("classifier", {}).items() if "ended_early" in s["counts"]}
    if judged:
        lines += ["The classifier in the loop, per training episode against the simulator's success at the same "
                  "state: episodes it ended as successes, of those the simulator calls failures (false ends), and "
                  "simulator successes it let run to the time limit (missed).", "",
                  "| seed | episodes | ended as successes | false ends | missed | simulator successes |",
                  "|---|---|---|---|---|---|"]
        for seed, s in sorted(judged.items(), key=lambda kv: int(kv[0])):
            c = s["counts"]
            lines.append(f"| {seed} | {c['episodes']} | {c['ended_early']} | {c['false_ends']} | {c['missed']} "
                         f"| {c['successes']} |")
        lines.append("")
    return lines + ["![success against environment steps](pusher_push_online.png)", ""]


def push_full_budget_section(name: str, payload: dict) -> list[str]:
    """A seed of the push stage at the issue's whole budget of 50,000 steps (bench/push_online.py --env-steps)."""
    return (["### The HIL-SERL stage on pusher_push at the whole budget", ""] + note_lines(payload)
            + source_lines(name, payload) + ["", hil_table(payload["arms"]), "",
                                             "![success against environment steps](pusher_push_online_full_budget.png)",
                                             ""])


# the variants of bench/push_bound.py: edits of the first pusher_push (bench/push_tasks)
WAVE_NOTE = ("`wave` is pusher_push as first shipped (the wave expert at 50 Hz; digest `f371e75b24e83718`, kept "
             "as bench/push_tasks/pusher_push_wave.yaml) and every other variant an edit of it; the shipped "
             "pusher_push is `orbit_direction_frame_rate20` but for its name. ")


def push_variants_table(variants: dict) -> list[str]:
    """The task-file variants of bench/push_bound.py: digest, rate, observation, the expert's success."""
    lines = ["| variant | digest | control period s | steps per episode | obs | expert's success |",
             "|---|---|---|---|---|---|"]
    for v, rec in variants.items():
        lines.append(f"| {v} | `{rec['task_digest']}` | {rec['control_period_s']:g} | {rec['max_steps']} "
                     f"| {rec['obs_dim']} | {rec['expert_success']:.2f} |")
    return lines


def push_bound_section(name: str, payload: dict) -> list[str]:
    """Behaviour cloning of pusher_push's expert alone: what bounds learning it from corrections
    (bench/push_bound.py)."""
    lines = ["## What bounds the HIL-SERL stage on pusher_push", "",
             "The online stage's actor learns the corrector's actions by a BC term beside its SAC objective, so how "
             "well a network of its width copies the scripted expert bounds what that term gives. Here it copies "
             "nothing else: behaviour cloning (`offline-rl train --algo bc --normalize-obs`) on logs of the expert "
             "alone (`offline-rl collect --expert-frac 1 --seed 1000`), for 30,000 gradient steps, then the "
             "deterministic policy on the 100 held-out resets. Failures: `near`, the puck ends within "
             f"{payload['near_within']:g} x success_within of the goal; `pushed`, it moved but ends further; "
             "`untouched`, it never moved. " + WAVE_NOTE
             + "Variants of the task file: `direction` adds the unit vectors puck - "
             "fingertip and goal - puck to the observation; `rate20` commands the arm at 20 Hz (control_period "
             "0.05 s, 60 steps: the same 3 s); `direction_rate20` both.", ""]
    lines += note_lines(payload)
    lines += source_lines(name, payload) + [""]
    lines += push_variants_table(payload["variants"])
    lines += ["", "| variant | expert episodes (transitions) | width | success [95 % Wilson] | failures: near / pushed "
              "/ untouched | final distance m, median / p75 |", "|---|---|---|---|---|---|"]
    for rec in payload["cells"].values():
        f, d = rec["failures"], rec["final_dist_m"]
        lines.append(f"| {rec['variant']} | {rec['expert_episodes']} ({rec['transitions']}) | {rec['hidden']} "
                     f"| {rec['success']:.2f} [{rec['ci'][0]:.2f}, {rec['ci'][1]:.2f}] | {f['near']} / {f['pushed']} / "
                     f"{f['untouched']} | {d['median']:.4f} / {d['p75']:.4f} |")
    online = payload.get("online", {})
    if online:
        lines += ["", "The online stage itself on the same variants (`offline-rl hil --online --in-process`, seed 0, "
                  "from each variant's `--algo auto` prior on its own 200-episode mix, 30 % expert, the scripted "
                  "corrector; success without intervention on the 100 held-out resets):", "",
                  "| variant | options | prior (its learner) | success along the run | best | at the end "
                  "| corrector's steps |", "|---|---|---|---|---|---|---|"]
        for v, rec in online.items():
            along = ", ".join(f"{p['success']:.2f}" for p in rec["curve"])
            lines.append(f"| {v} | `{rec['options']}` | {rec['prior_success']:.2f} ({rec['prior_algorithm']}) "
                         f"| {along} (every {rec['curve'][1]['env_steps']:,} steps) | {rec['best']:.2f} "
                         f"| {rec['final_success']:.2f} after {rec['env_steps']:,} | {rec['human_steps']:,} |")
    return lines + [""]


def push_dagger_section(name: str, payload: dict) -> list[str]:
    """Full DAgger on pusher_push: the most a corrector's labels teach an actor (bench/push_bound.py
    --dagger)."""
    lines = ["## The most a corrector's labels teach on pusher_push (full DAgger)", "",
             "A person, or the scripted corrector, labels only the states of a takeover. Here the expert labels "
             "every state the policy visits (DAgger), which bounds what any corrector's labels can teach an actor "
             "of that width: behaviour cloning (deterministic, fp32, `--normalize-obs`) on the expert episodes of "
             "the mix's expert share, then rounds in which the policy acts and BC goes on from its last weights on "
             "every label so far; success of the deterministic policy on the 100 held-out resets, against "
             "environment steps (the demonstrations' included). " + WAVE_NOTE
             + "`direction_frame` adds to the observation the unit "
             "vectors puck - fingertip and goal - puck and `along_across: [fingertip, puck, goal]`; `_rate20` "
             "commands the arm at 20 Hz; `_elbow` adds where the forearm starts (`elbow`, the body link2), seen "
             "from the puck and along its line to the goal; `_table` adds the puck and the goal in the arm's base "
             "frame (`vector: puck`, `vector: goal`); `orbit_` has the scripted expert, whose actions are the "
             "labels, go round the puck in the push line's frame (`sim.push.approach: orbit`) instead of through "
             "the arm's joint space. The last round's failures: the puck ends within 3 x "
             "success_within of the goal (near), moved but further (pushed), or never moved (untouched).", ""]
    lines += note_lines(payload)
    lines += source_lines(name, payload) + [""]
    lines += push_variants_table(payload["variants"])
    lines += ["", "| variant | width | demonstrations, then episodes x BC steps per round | success (environment "
              "steps) along the rounds | best | labels | last round's failures (near / pushed / untouched) |",
              "|---|---|---|---|---|---|---|"]
    for rec in payload["dagger"].values():
        along = ", ".join(f"{p['success']:.2f} ({p['env_steps']:,})" for p in rec["curve"])
        failed = rec.get("last_failures")
        failures = f"{failed['near']} / {failed['pushed']} / {failed['untouched']}" if failed else "-"
        lines.append(f"| {rec['variant']} | {rec['hidden']} | {rec['demos']}, then {rec['episodes_per_round']} x "
                     f"{rec['bc_steps_per_round']:,} | {along} | {rec['best']:.2f} | {rec['labels']:,} | {failures} |")
    online = payload.get("online", {})
    if online:
        lines += ["", "The online stage on the same variants, where the scripted corrector labels only its takeovers, "
                  "or with `--action-labels` also every state it leaves to the policy (`offline-rl hil --online "
                  "--in-process`, or over ROS with the learner on the arm's raw topics where the options end in "
                  "`--over-ros`; seed 0 unless `--seed`, each variant's `--algo auto` prior on its own 200-episode "
                  "mix, 30 % expert; success without intervention on the 100 held-out resets):", "",
                  "| variant | options | prior (its learner) | success (environment steps) along the run | at the end "
                  "| corrector's steps |", "|---|---|---|---|---|---|"]
        for rec in online.values():
            along = ", ".join(f"{p['success']:.2f} ({p['env_steps']:,})" for p in rec["curve"][1:])
            lines.append(f"| {rec['variant']} | `{rec['options']}` | {rec['prior_success']:.2f} "
                         f"({rec['prior_algorithm']}) | {along} | {rec['final_success']:.2f} | {rec['human_steps']:,} |")
    return lines + [""]


def pusher7_probes_section(name: str, payload: dict) -> list[str]:
    lines = ["## What bounds the HIL-SERL stage on pusher7_reach", "",
             "The in-process stage on seed 0 at the full budget (20,000 environment steps), one setting changed at a "
             "time against the stage's defaults; success without intervention of the deterministic policy on the 100 "
             "held-out resets every 2,500 steps (Wilson 95 % at the best point). The last column looks at the final "
             "policy's failed episodes: how many came within 0.1 m of the goal (the success radius is 0.05 m) and the "
             "median of their closest approach. With the stage's own settings nothing passes 0.9: z-scored "
             "observations, the expert's episodes imitated, the entropy weight, the horizon or the corrector's "
             "patience each end between 0.45 and 0.86. Only a heavy anchor on the expert's and the corrector's "
             "actions (BC weight 30 to 100, the rates decaying over the budget) lifts it past 0.9, and with a "
             "quarter of each batch offline besides it holds 0.96 from 15,000 steps on. Around that setting "
             "(BC weight 300, a tenth offline, 4 gradient steps per environment step, the corrector steering with "
             "a Cartesian stick, a shaky hand) the stage ends between 0.86 and 0.95: weights versions swing by a "
             "few points on the same 100 resets, and the failures stay near misses. Those rows (`@b0d9138b871487b8`) "
             "ran on the task file before its observation gained `direction: [goal, fingertip]`, the unit vector "
             "from fingertip to goal beside their difference. Near the goal that difference is a few hundredths of "
             "its spread, and the policy crawled there. With the direction besides (the rows without the suffix), the "
             "stage's own defaults reach 0.98 at 7,500 steps and end at 0.96, and the heavy anchor holds 0.96 to "
             "0.99 from 2,500 steps on.", ""]
    lines += note_lines(payload)
    return lines + source_lines(name, payload) + ["", probes_table(payload), ""]


# ----------------------------------------------------------------------------- the best prior

CHAPTER_8000 = {"BC": "0.03 / 0.07 / 0.05", "AWAC": "0.27 / 0.20 / 0.21"}  # the chapter's 8000-step runs


def curves_table(curves: dict, expert_frac: float) -> str:
    """Every learner at the same training time: its final point per seed, pooled over seeds
    (bench/prior_report.py prints it too)."""
    by_label: dict[str, list] = {}
    for rec in curves.values():
        if rec["points"] and rec["expert_frac"] == expert_frac:
            by_label.setdefault(rec["label"], []).append(rec)
    lines = ["| learner | training s | steps, seeds 0 / 1 / 2 | success | pooled [95 % CI] | final distance m "
             "| chapter, 8000 steps |", "| --- | --- | --- | --- | --- | --- | --- |"]
    finals = {label: [p for r in sorted(recs, key=lambda r: r["seed"]) for p in r["points"] if p["fraction"] == 1.0]
              for label, recs in by_label.items()}
    pooled = {label: sum(p["successes"] for p in pts) / sum(p["episodes"] for p in pts) for label, pts in finals.items()}
    for label in sorted(by_label, key=lambda lb: -pooled[lb]):  # the best first
        recs, pts = by_label[label], finals[label]
        s, n = sum(p["successes"] for p in pts), sum(p["episodes"] for p in pts)
        a, b = wilson_ci(s, n)
        budget = max(r["budget_s"] for r in recs)
        steps = per_seed(str(p["steps"]) for p in pts)
        success = per_seed(f"{p['success_rate']:.2f}" for p in pts)
        dist = per_seed(f"{p['mean_final_dist']:.3f}" for p in pts)
        chapter = CHAPTER_8000.get(label, "-") if expert_frac == 0.3 else "-"
        lines.append(f"| {label} | {budget:.0f} | {steps} | {success} | {s / n:.3f} [{a:.3f}, {b:.3f}] | {dist} | {chapter} |")
    return "\n".join(lines)


def musthold_table(musthold: dict) -> str:
    lines = ["| seed | expert share | `--algo auto`: success [95 % Wilson] | final distance m | whole command s "
             "| steps (learner) | chapter's AWAC loop s, by torch threads | within the faster |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for _, r in sorted(musthold.items()):
        e = r["eval"]
        threads = ", ".join(f"{t}: {s}" for t, s in sorted(r["chapter_awac_s"].items()))
        lines.append(f"| {r['seed']} | {r['expert_frac']} | {e['success_rate']:.2f} [{e['wilson_ci_lo']:.2f}, "
                     f"{e['wilson_ci_hi']:.2f}] | {e['mean_final_dist']:.3f} | {r['auto_command_s']} "
                     f"| {r['steps']} ({r['algorithm']}) | {threads} | {'yes' if r['within'] else 'NO'} |")
    return "\n".join(lines)


def prior_section(name: str, payload: dict) -> list[str]:
    out = ["## The best prior (`--algo auto`)", "",
           "On the report's data (datasets of seeds 0, 1, 2; the chapter's 100 pooled held-out rollouts each). "
           "`musthold`: `offline-rl train --algo auto` with its default budget, timed as a whole command, beside "
           "the chapter's AWAC loop timed in the same process. `curves`: every learner trained for the same "
           "seconds (the chapter's AWAC loop on that machine), steps from its measured step rate.", ""]
    out += source_lines(name, payload) + ["", musthold_table(payload.get("musthold", {})), ""]
    for frac, png in ((0.3, "prior_curves.png"), (1.0, "prior_curves_expert.png")):
        if any(r["expert_frac"] == frac for r in payload.get("curves", {}).values()):
            out += [f"Every learner at equal training time, {frac:.0%} expert episodes:", "",
                    curves_table(payload["curves"], frac), "", f"![success against seconds of training]({png})", ""]
    return out


def selection_table(records: list[dict]) -> str:
    """One row per (candidate, expert share): success on the validation resets, data seed
    10 / 11, at each step count (bench/prior_selection.py --table prints it too)."""
    rows: dict[tuple, dict[int, dict[int, float]]] = {}
    for r in records:
        rows.setdefault((r["candidate"], r.get("expert_frac", 0.3)), {}).setdefault(r["steps"], {})[r["data_seed"]] = \
            r["success_rate"]
    steps = sorted({s for cells in rows.values() for s in cells})
    lines = ["| candidate | expert share | " + " | ".join(f"{s // 1000}k" if s >= 1000 else str(s) for s in steps) + " |",
             "|---|---|" + "---|" * len(steps)]
    for (name, frac), cells in rows.items():
        out = []
        for s in steps:
            got = cells.get(s, {})
            out.append(" / ".join(f"{got[d]:.2f}" for d in sorted(got)) if got else "")
        lines.append(f"| {name} | {frac} | " + " | ".join(out) + " |")
    return "\n".join(lines)


def selection_section(name: str, payload: dict) -> list[str]:
    return ["## Choosing the prior (validation data)", "",
            "Candidate learners on validation data only: the chapter's dataset recipe collected with data seeds 10 "
            "and 11, scored on reset seeds 600000-600199; a cell is data seed 10 / 11. Names: `fbc30` filtered BC on "
            "the top 30 % of episodes by return; `goal` on the episodes that end at the goal; `_norm` z-scored "
            "observations; `_lr1e3` / `_lr3e3` learning rate; `_cos` cosine decay (one run per length).", ""] + \
        source_lines(name, payload) + ["", selection_table(payload["records"]), ""]


def gpu_ensemble_section(name: str, payload: dict) -> list[str]:
    rows = ["| round | one seed, steps/s | three seeds as one ensemble, member-steps/s | ratio |", "| --- | --- | --- | --- |"]
    rows += [f"| {i + 1} | {r['one_seed_steps_per_s']:.0f} | {r['three_seeds_member_steps_per_s']:.0f} "
             f"| {r['three_seeds_member_steps_per_s'] / r['one_seed_steps_per_s']:.2f}x |" for i, r in enumerate(payload["rounds"])]
    return ["## AWAC on a GPU: one seed against three as one ensemble", "", *source_lines(name, payload), "", *rows, ""]


def ros_pipeline_section(name: str, payload: dict) -> list[str]:
    """bench/pusher7_ros.py: a task recorded over ROS from raw topics, learnt, served by the policy node."""
    st, ds, rec = payload["settings"], payload["dataset"], payload["recording"]
    rows = ["| policy | trained | in process | closed loop over ROS (policy node) | episodes agreeing |",
            "| --- | --- | --- | --- | --- |"]

    def rate(r: dict) -> str:
        return f"{r['successes']}/{r['episodes']} = {r['success_rate']:.2f} [{r['wilson'][0]:.2f}, {r['wilson'][1]:.2f}]"

    for algo, r in payload["learners"].items():
        t = r["trained"]
        plan = f", auto chose {t['algorithm']}" if algo == "auto" else ""
        rows.append(f"| {algo} | {t['steps']} steps{plan}, {t['wall_s']:.0f} s | {rate(r['in_process'])} "
                    f"| {rate(r['over_ros'])} | {r['episodes_agreeing']}/{r['over_ros']['episodes']} |")
    rows.append(f"| expert (scripted) | - | {rate(payload['expert_in_process'])} | - | - |")
    equal = ds["rows_equal_per_field"]
    return [f"## {payload['task']} over ROS: recorded from raw topics, learnt, served", "",
            f"{st['episodes']} episodes ({st['expert_frac']:.0%} by the scripted expert, then uniform random), "
            f"{payload['mode']} sim driven through `{'`, `'.join(t for t in rec['bag_topics'] if 'command' in t)}` by a "
            f"scripted controller and recorded by the passive recorder on sim time: "
            f"`{'`, `'.join(rec['bag_topics'])}` (no `/pusher/transition`); `offline-rl dataset --from-topics` made "
            f"{ds['rows_from_topics']} transitions of the {ds['rows_in_process']} `offline-rl collect` rolls out in "
            f"process, {min(equal.values())} of them equal to those rows field by field (the others: each episode's "
            f"last step, whose next state the topics never show). Success on the held-out resets "
            f"{st['eval_seeds'][0]}..{st['eval_seeds'][1]} with Wilson 95 % intervals; over ROS the policy node "
            "answers `joint_states` + `goal` on the controller's topic of a lockstep sim.", "",
            *source_lines(name, payload), "", *rows, ""]


def flat_value(value) -> str | None:
    """A scalar (or a short list of scalars) as a table cell; None for anything larger."""
    if isinstance(value, bool) or value is None:
        return str(value).lower()
    if isinstance(value, (int, float, str)):
        return cell(f"{value:.6g}" if isinstance(value, float) else str(value))
    if isinstance(value, list) and len(value) <= 8 and all(isinstance(v, (int, float, str)) for v in value):
        return cell(", ".join(f"{v:.6g}" if isinstance(v, float) else str(v) for v in value))
    return None


FACTS_SHOWN_ELSEWHERE = {"command", "commands", "measured_at", "machine", "cpu", "cpu_flags", "cores", "note",
                         "provenance", "title"}


def flat_section(name: str, payload: dict) -> list[str]:
    """A file of one measurement (a bench script's): its scalar figures, one level deep."""
    title = payload.get("title") or name.removesuffix(".json").replace("_", " ")
    rows = []
    for key, value in payload.items():
        if key in FACTS_SHOWN_ELSEWHERE:
            continue
        if isinstance(value, dict):
            rows += [(f"{key}.{k}", flat_value(v)) for k, v in value.items() if flat_value(v) is not None]
        elif flat_value(value) is not None:
            rows.append((key, flat_value(value)))
    lines = [f"## {title[0].upper()}{title[1:]}", "", *source_lines(name, payload), ""]
    lines += note_lines(payload)
    lines += ["| figure | value |", "| --- | --- |", *(f"| {k} | {v} |" for k, v in rows), ""]
    return lines


SECTIONS = {  # file -> its section, in the page's order (the speed sections follow the chapter's)
    "chapter_report.json": chapter_section,
    "prior_report.json": prior_section,
    "prior_selection.json": selection_section,
    "hil_online.json": hil_section,
    "multi_actor.json": multi_actor_section,
    "pusher7_online.json": pusher7_online_section,
    "pusher7_online_probes.json": pusher7_probes_section,
    "pusher_push_report.json": push_experiment_section,
    "pusher_push_online.json": push_online_section,
    "pusher_push_online_full_budget.json": push_full_budget_section,
    "pusher_push_bound.json": push_bound_section,
    "pusher_push_dagger.json": push_dagger_section,
    "crash_safety.json": crash_section,
    "gpu_ensemble.json": gpu_ensemble_section,
    "pusher7_ros.json": ros_pipeline_section,
}


# ----------------------------------------------------------------------------- the page

def load(bench: Path = BENCH) -> dict[str, dict]:
    return {p.name: json.loads(p.read_text()) for p in sorted(bench.glob("*.json"))}


def render(files: dict[str, dict]) -> str:
    # a file no section knows is a bench script's single measurement: its figures as they are,
    # once it says what made them and where
    flat = [n for n, p in files.items() if not is_bench_run(p) and n not in SECTIONS]
    for name in flat:
        if missing_facts(files[name]):
            raise SystemExit(f"bench/{name}: no section of bench/results_page.py renders it, and it does not say "
                             f"its {' and '.join(missing_facts(files[name]))} for the page's generic table")
    out = ["# Benchmark results", "",
           "Generated by `python bench/results_page.py` from the JSON files in `bench/` (`make bench` runs it last); "
           "do not edit it by hand: `tests/test_results_page.py` checks that it is what the JSON gives. What each "
           "figure measures, its reference and the method: [README.md](README.md). Ratios are \"times better than the "
           "reference\" (ours / reference for rates, reference / ours for times); timings on a shared machine drift, "
           "so compare the ratios.", ""]
    speed, not_current = bench_sections({n: p for n, p in files.items() if is_bench_run(p)})
    sections = []
    for name, section in SECTIONS.items():
        if name == "chapter_report.json":  # the chapter's figures first, then speed, then the rest
            sections += section(name, files[name]) + speed if name in files else speed
        elif name in files:
            sections += section(name, files[name])
    for name in flat:
        sections += flat_section(name, files[name])
    contents = [("- " if line.startswith("## ") else "  - ") + line.lstrip("#").strip()
                for line in sections if line.startswith(("## ", "### "))]
    out += ["Contents:"] + contents + [""] + sections
    if not_current:
        out += ["## Files with no current figure", "",
                "Every figure of these files was measured again later on the same configuration: "
                + ", ".join(f"[{n}]({n})" for n in not_current) + ".", ""]
    return "\n".join(out).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if bench/RESULTS.md differs from what the JSON gives")
    args = ap.parse_args(argv)
    page = render(load())
    if args.check:
        if PAGE.read_text() != page:
            print("bench/RESULTS.md is not what bench/*.json give: run python bench/results_page.py", file=sys.stderr)
            return 1
        return 0
    write_text_atomic(PAGE, page)
    print(f"wrote {PAGE.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
