"""`make demo`: the whole pipeline over ROS 2, on the shipped bag, in a few minutes.

1. record a small bag: sim node (lockstep) + recorder node, over real DDS
   (``pusher_bringup/launch/record.launch.yaml``);
2. train BC and AWAC from ``bags/mix.db3`` with the trainer node (both at once), then
   the best prior (``--algo auto``);
3. serve AWAC with the policy node and run the sim closed loop on the chapter's
   100 held-out reset seeds (``serve.launch.yaml``);
4. print the comparison: BC vs AWAC with Wilson intervals and the Newcombe
   difference interval (the chapter's experiment), AWAC over ROS next to AWAC
   in-process, and the best prior beside them.

Everything lands in ``runs/demo/``. The nodes run as separate processes on a private
DDS domain and are stopped by pid at the end, also on errors and Ctrl-C. This module
only starts processes; it imports no ROS.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from contextlib import ExitStack
from pathlib import Path

from ..common import seeds
from ..common.errors import UserError
from ..common.atomic import write_json_atomic
from ..learners.config import TrainConfig
from ros2_shim.ament_index import ros2_run, venv_bin

from .processes import LaunchedProcesses, RosProcess, isolated_ros_env
from ..evaluation.stats import newcombe_diff_ci

EVAL_SEED = seeds.HELD_OUT
EVAL_EPISODES = 100


def check_ros_installed() -> str:
    ros2 = venv_bin("ros2")
    if not ros2.exists():
        raise UserError(f"{ros2}: the ros2 command is not installed; run `make setup`")
    return str(ros2)


def say(msg: str) -> None:
    print(msg, flush=True)


def wait_for(proc: RosProcess, timeout: float, what: str) -> int:
    """Exit status of ``proc``; a clear error (and the log to read) when it fails or hangs."""
    status = proc.wait(timeout=timeout)
    if status is None:
        raise UserError(f"{what} did not finish within {timeout:.0f} s; see {proc.log_path}")
    if status != 0:
        raise UserError(f"{what} failed (exit {status}); see {proc.log_path}")
    return status


def last_progress(proc: RosProcess) -> str:
    lines = [ln.strip() for ln in proc.output().splitlines() if ln.strip().startswith("step")]
    return lines[-1] if lines else "starting"


def run_demo(out: Path, bag: Path, steps: int, record_episodes: int, seed: int) -> int:
    if not bag.exists():
        raise UserError(f"{bag}: no such bag; regenerate it with `make bag`")
    ros2 = check_ros_installed()
    out.mkdir(parents=True, exist_ok=True)
    logs = out / "logs"
    logs.mkdir(exist_ok=True)
    env = isolated_ros_env()
    say(f"pusher-rl demo: ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']} (localhost only), outputs in {out}/")
    t_start = time.perf_counter()

    # 1. record a small bag over DDS
    recorded = out / "recorded.db3"
    if recorded.exists():
        recorded.unlink()
    say(f"\n[1/4] recording {record_episodes} episodes over ROS: sim (lockstep) + recorder -> {recorded}")
    record = {"out": recorded, "episodes": record_episodes, "expert_frac": 0.3, "seed": seed}
    with LaunchedProcesses.of("pusher_bringup", "record.launch.yaml", record, env, logs / "record").start() as launched:
        if launched.wait(timeout=300) != 0:
            raise UserError(f"the recorder node failed; see {launched['recorder'].log_path}")
    info = subprocess.run([ros2, "bag", "info", str(recorded)], env=env, capture_output=True, text=True, timeout=60)
    say(info.stdout.rstrip() or info.stderr.rstrip())

    # 2. train BC and AWAC with the trainer node side by side (one core each), then the best
    # prior alone (the first time on a machine it times the chapter's loop for its budget)
    say(f"[2/4] training BC and AWAC on {bag} with the trainer node ({steps} steps each, in parallel), "
        f"then the best prior (--algo auto)")
    for group in (("bc", "awac"), ("auto",)):
        trainers = {}
        for algo in group:
            length = [] if algo == "auto" else ["--steps", steps]  # auto: as many as it plans
            trainers[algo] = RosProcess(
                ros2_run("trainer", "node", "--bag", bag, "--algo", algo, *length, "--seed", seed,
                         "--out", out / algo, "--eval-episodes", EVAL_EPISODES, "--eval-seed", EVAL_SEED + seed),
                env, logs / f"trainer_{algo}.log")
        with ExitStack() as running:
            for t in trainers.values():
                running.enter_context(t)
            last, shown = time.perf_counter(), ""
            while any(t.running() for t in trainers.values()):
                time.sleep(0.5)
                if time.perf_counter() - last > 15:
                    last = time.perf_counter()
                    progress = " | ".join(f"{algo}: {last_progress(t)}" for algo, t in trainers.items())
                    if progress != shown:  # a line only when a trainer moved on
                        say("      " + progress)
                        shown = progress
            for algo, t in trainers.items():
                wait_for(t, 10, f"the trainer node ({algo})")
    metrics = {algo: json.loads((out / algo / "metrics.json").read_text()) for algo in ("bc", "awac", "auto")}

    # 3. serve AWAC and close the loop over DDS
    closed_loop = out / "closed_loop_awac.json"
    say(f"[3/4] serving AWAC with the policy node; sim closed loop on {EVAL_EPISODES} held-out seeds "
        f"({EVAL_SEED + seed}..{EVAL_SEED + seed + EVAL_EPISODES - 1})")
    if closed_loop.exists():
        closed_loop.unlink()
    serve = {"checkpoint": out / "awac" / "policy.pt", "seed": EVAL_SEED + seed, "episodes": EVAL_EPISODES,
             "summary": closed_loop}
    with LaunchedProcesses.of("pusher_bringup", "serve.launch.yaml", serve, env, logs / "serve").start() as launched:
        if launched.wait(timeout=600) != 0:
            raise UserError(f"the closed-loop sim failed; see {launched['sim'].log_path}")
    if not closed_loop.exists():
        raise UserError(f"the closed-loop sim wrote no summary {closed_loop}; see {launched['sim'].log_path}")
    ros_summary = json.loads(closed_loop.read_text())

    # 4. the table
    bc, awac, auto = metrics["bc"]["eval"], metrics["awac"]["eval"], metrics["auto"]["eval"]
    lo, hi = newcombe_diff_ci(awac["successes"], awac["episodes"], bc["successes"], bc["episodes"])
    verdict = "AWAC beats BC" if lo > 0 else ("BC beats AWAC" if hi < 0 else "no significant difference")
    rows = [
        ("BC (in-process)", bc["success_rate"], bc["wilson_ci_lo"], bc["wilson_ci_hi"], bc["mean_final_dist"]),
        ("AWAC (in-process)", awac["success_rate"], awac["wilson_ci_lo"], awac["wilson_ci_hi"], awac["mean_final_dist"]),
        ("AWAC over ROS (closed loop)", ros_summary["success_rate"], None, None, ros_summary["mean_final_dist"]),
        (f"best prior (auto: {metrics['auto']['algorithm']})", auto["success_rate"], auto["wilson_ci_lo"],
         auto["wilson_ci_hi"], auto["mean_final_dist"]),
    ]
    say(f"\n[4/4] results on {EVAL_EPISODES} held-out rollouts (trained on {bag})")
    say(f"  {'policy':<30} {'success':>8}  {'95% Wilson CI':>15}  {'final dist (m)':>14}")
    for name, rate, clo, chi, dist in rows:
        ci = f"[{clo:.2f}, {chi:.2f}]" if clo is not None else ""
        say(f"  {name:<30} {rate:>8.2f}  {ci:>15}  {dist:>14.4f}")
    say(f"  AWAC - BC success: {awac['success_rate'] - bc['success_rate']:+.2f}, "
        f"Newcombe 95% CI [{lo:+.2f}, {hi:+.2f}] -> {verdict}")
    summary = {
        "bc": bc, "awac": awac, "awac_closed_loop": ros_summary, "auto": auto, "auto_plan": metrics["auto"].get("plan"),
        "diff_ci_lo": round(lo, 6), "diff_ci_hi": round(hi, 6), "gap_significant": bool(lo > 0 or hi < 0),
        "recorded_bag": str(recorded), "wall_seconds": round(time.perf_counter() - t_start, 1),
    }
    write_json_atomic(out / "summary.json", summary)
    say(f"\nwrote {out}/summary.json, {out}/{{bc,awac,auto}}/policy.pt + metrics.json + training_curve.png, "
        f"{recorded}; logs in {logs}/  ({summary['wall_seconds']:.0f} s)")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m offline_rl_core.pipelines.demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="runs/demo", help="output directory (default: %(default)s)")
    parser.add_argument("--bag", default="bags/mix.db3", help="training bag (default: %(default)s)")
    parser.add_argument("--steps", type=int, default=TrainConfig.steps,
                        help="gradient steps per learner (default: the chapter's, %(default)s)")
    parser.add_argument("--record-episodes", type=int, default=10, help="episodes to record over ROS (default: %(default)s)")
    parser.add_argument("--seed", type=seeds.seed_arg, default=0)
    args = parser.parse_args(argv)
    try:
        return run_demo(Path(args.out), Path(args.bag), args.steps, args.record_episodes, args.seed)
    except UserError as exc:
        print(f"demo: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("demo: interrupted; all nodes stopped", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
