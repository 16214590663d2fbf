"""pusher7_reach as a user would run it (issue 23): recorded over ROS from raw topics, learnt
from the topics, served by the policy node into the sim through the controller topic.

1. Record: the sim hosts pusher7_reach in lockstep (reset seeds SEED..); a scripted
   controller (ros_ws/tools/bench_probes/scripted_controller.py: the task's expert for the
   first 30 % of the episodes, uniform random actions after, as `offline-rl collect` rolls
   them out) answers each `joint_states` on the controller's command topic; the passive
   recorder writes the raw topics only (the state, the goal, the commands, the task's
   description: no `pusher/transition`).
2. `offline-rl dataset --from-topics TASK` builds the transitions from those topics; they
   are compared, row by row, with `offline-rl collect`'s in-process rollout of the same
   episodes.
3. `offline-rl train` per learner (BC, AWAC, `--algo auto`), seed 0, on the dataset.
4. Each policy on the 100 held-out resets (500000..): in process (`offline-rl eval`'s
   rollouts) and closed loop over ROS (the policy node answering `joint_states` + `goal`
   on the controller's command topic of a lockstep sim started at reset seed 500000; the
   outcome of each episode from the sim's own transitions, recorded beside); success with
   Wilson intervals and whether the two agree episode by episode. The expert's, in process,
   beside.

    nice -n 5 .venv/bin/python bench/pusher7_ros.py                       # the figure -> bench/pusher7_ros.json
    ... --keep DIR --algos awac --steps 2000 --resume                     # more learners on DIR's recording
    .venv/bin/python bench/pusher7_ros.py --episodes 5 --eval-episodes 3 --steps 200 --out /tmp/p7.json  # a look
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from offline_rl_core.benchmarks.harness import machine_info, utc_now
from offline_rl_core.benchmarks.ros_procs import bench_node, isolate, ros2_command, ros_missing
from offline_rl_core.commands.cli import main as cli
from offline_rl_core.common.atomic import write_json_atomic
from offline_rl_core.common.seeds import HELD_OUT
from offline_rl_core.data.bag import read_transitions
from offline_rl_core.data.bag.info import bag_info
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.evaluation.rollouts import evaluate_policy, rollout_task
from offline_rl_core.evaluation.stats import wilson_ci
from offline_rl_core.serving.policy import load_policy
from offline_rl_core.task.spec import JOINT_STATE, POSE_STAMPED, load_task

REPO = Path(__file__).resolve().parents[1]
CONTROLLER = REPO / "ros_ws" / "tools" / "bench_probes" / "scripted_controller.py"
OUT = REPO / "bench" / "pusher7_ros.json"
# Lockstep: a state the sim republishes while its (headerless) answer is in flight would get
# that answer again from the policy node, taken for the next state's; a long period makes
# that never happen here. (The scripted controller answers a state once: while recording,
# the sim republishes often, so that readers matched late get the first state.)
REPUBLISH_S = 5.0


def raw_topics(task) -> list[str]:
    """What a user records of this arm: its state, goal, the controller's commands, the
    tracked points it publishes, and the task's description."""
    return [task.state.topic, task.goal.topic, task.command.topic,
            *[p.topic for p in task.points if p.topic], "task_description"]


def typed_topics(task) -> list[str]:
    """The recorder's --types: the arm's topics subscribed from the start, not when discovery
    finds their publishers, so the first states are in the bag."""
    command = "sensor_msgs/msg/JointState" if task.command.type == JOINT_STATE else "std_msgs/msg/Float64MultiArray"
    goal = {JOINT_STATE: "sensor_msgs/msg/JointState", POSE_STAMPED: "geometry_msgs/msg/PoseStamped"}.get(
        task.goal.type, "geometry_msgs/msg/PointStamped")
    return [f"{task.state.topic}:sensor_msgs/msg/JointState", f"{task.goal.topic}:{goal}", f"{task.command.topic}:{command}"]


def sim_args(task_arg: str, seed: int, episodes: int, *extra: str, republish_s: float = REPUBLISH_S) -> list[str]:
    return [ros2_command(), "run", "sim", "node", "--ros-args", "-p", f"task:={task_arg}", "-p", "mode:=lockstep",
            "-p", f"seed:={seed}", "-p", f"episodes:={episodes}", "-p", f"republish_period:={republish_s}", *extra]


def record(task, task_arg: str, episodes: int, expert_frac: float, seed: int, bag: Path, logs: Path,
           pace_s: float) -> dict:
    """Drive the lockstep sim with the scripted controller; the passive recorder keeps the raw topics.

    Float64MultiArray commands have no header, so the join pairs them with states by the
    bag's receive times (the task's join.stamps: receive), a control period apart: the
    recorder runs on sim time (the sim's /clock), and the controller leaves ``pace_s`` of
    wall time between commands so the recorder has taken each command before the /clock of
    the step it causes (a message still queued behind a newer /clock gets that newer time)."""
    t0 = time.monotonic()
    with bench_node([ros2_command(), "run", "recorder", "node", "--passive", "--out", str(bag),
                     "--topics", *raw_topics(task), "--types", *typed_topics(task), "--ros-args",
                     "-p", "use_sim_time:=true"], logs / "recorder.log") as rec, \
            bench_node(sim_args(task_arg, seed, episodes, "-p", "wait_for_readers:=[recorder]", republish_s=0.2),
                       logs / "record_sim.log") as sim:  # its first state once the recorder reads the states
        if not rec.wait_for_output("recording passively", 60):
            raise RuntimeError(f"the recorder did not start: {rec.output()[-600:]}")
        # 2 readers of the commands (the sim, the recorder) before the first one is sent
        with bench_node([sys.executable, str(CONTROLLER), task_arg, str(episodes), str(expert_frac), str(seed), "2",
                         str(pace_s)], logs / "controller.log") as ctl:
            deadline = time.monotonic() + 600 + episodes * task.episodes.max_steps * (pace_s + 0.05)
            while ctl.poll() is None and sim.poll() is None and time.monotonic() < deadline:
                time.sleep(0.5)
            if ctl.poll() not in (None, 0):
                raise RuntimeError(f"the scripted controller failed: {ctl.output()[-600:]}")
            if sim.wait(timeout=60) is None:
                raise RuntimeError(f"the sim did not finish its {episodes} episodes: {sim.output()[-600:]}")
            ctl.stop(timeout=10)
        time.sleep(1.0)  # what is in flight reaches the recorder (it writes every message it received on stop)
        rc = rec.stop(timeout=30)
    if rc != 0:
        raise RuntimeError(f"recorder exit {rc}: {rec.output()[-600:]}")
    topics = sorted(t.name for t in bag_info(bag).topics)
    return {"bag_topics": topics, "wall_s": round(time.monotonic() - t0, 1), "pace_s": pace_s,
            "controller": json.loads(ctl.output().strip().splitlines()[-1])}


def same_rows(topics, in_process) -> dict:
    """The dataset built from the topics against the in-process rollout, row by row (matched
    by episode and step: the join has no row for a step whose next state never came, each
    episode's last, where the sim publishes the next episode's first state instead)."""
    where = {(int(e), int(t)): i for i, (e, t) in enumerate(zip(in_process.episode, in_process.step))}
    index = np.array([where.get((int(e), int(t)), -1) for e, t in zip(topics.episode, topics.step)])
    found = index >= 0
    fields = ("obs", "action", "reward", "next_obs", "terminated", "success")
    equal = {f: int(np.all(getattr(topics, f)[found] == getattr(in_process, f)[index[found]],
                             axis=tuple(range(1, getattr(topics, f).ndim))).sum()) for f in fields}
    missing = sorted(set(range(len(in_process))) - set(index[found].tolist()))
    return {"rows_from_topics": len(topics), "rows_in_process": len(in_process), "rows_matched": int(found.sum()),
            "rows_equal_per_field": equal,
            "in_process_rows_missing_are_episode_ends": bool(np.all(in_process.truncated[missing]
                                                                   | in_process.terminated[missing]))}


def serve(task, task_arg: str, checkpoint: Path, episodes: int, logs: Path, name: str) -> dict:
    """The policy node drives the lockstep sim through the controller's command topic; the
    sim's transitions (recorded beside, not used by the policy) give each episode's outcome."""
    bag, summary = logs / f"serve_{name}.db3", logs / f"serve_{name}_sim.json"
    bag.unlink(missing_ok=True)
    t0 = time.monotonic()
    with bench_node([ros2_command(), "run", "recorder", "node", "--passive", "--episodes", str(episodes),
                     "--topics", "pusher/transition", "--out", str(bag)], logs / f"serve_{name}_recorder.log") as rec, \
            bench_node([ros2_command(), "run", "policy", "node", "--checkpoint", str(checkpoint), "--ros-args",
                        "-p", f"task:={task_arg}", "-p", "mode:=lockstep"], logs / f"serve_{name}_policy.log") as pol:
        if not pol.wait_for_output("serving", 120) or not rec.wait_for_output("recording passively", 60):
            raise RuntimeError(f"policy / recorder did not start: {pol.output()[-400:]} {rec.output()[-400:]}")
        # the sim holds its first state until the recorder reads its transitions
        with bench_node(sim_args(task_arg, HELD_OUT, episodes, "-p", f"summary:={summary}",
                                 "-p", "wait_for_subscribers:=1"), logs / f"serve_{name}_sim.log") as sim:
            if sim.wait(timeout=600 + episodes * task.episodes.max_steps * 0.05) is None:
                raise RuntimeError(f"the served episodes did not finish: {sim.output()[-600:]}")
            if rec.wait(timeout=60) is None:
                raise RuntimeError(f"the recorder missed episode ends: {rec.output()[-600:]}")
    rows = read_transitions(bag)
    success = np.array([rows.success[rows.episode == e].any() for e in range(episodes)])
    sim_summary = json.loads(summary.read_text())
    return {"success": success, "sim_summary": sim_summary, "steps": len(rows), "wall_s": round(time.monotonic() - t0, 1)}


def rate(k: int, n: int) -> dict:
    lo, hi = wilson_ci(k, n)
    return {"successes": int(k), "episodes": n, "success_rate": round(k / n, 6), "wilson": [round(lo, 6), round(hi, 6)]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="pusher7_reach")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--expert-frac", type=float, default=0.3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--algos", nargs="+", default=["bc", "awac", "auto"])
    parser.add_argument("--steps", type=int, default=None, help="gradient steps of bc / awac (default: train's); auto plans its own")
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--pace-s", type=float, default=0.01, help="recording: wall seconds between commands")
    parser.add_argument("--auto-budget-s", type=float, default=None,
                        help="--algo auto's --budget-s (default: train's, the chapter's AWAC loop time here)")
    parser.add_argument("--keep", type=Path, help="keep the bags, checkpoints and logs here")
    parser.add_argument("--resume", action="store_true",
                        help="with --keep: reuse its recording (raw.db3) and add these learners to --out's")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    why = ros_missing()
    if why:
        print(f"pusher7_ros: {why}", file=sys.stderr)
        return 2
    isolate()
    task = load_task(args.task)
    task_arg = args.task
    result = {"command": "python bench/pusher7_ros.py " + " ".join(argv if argv is not None else sys.argv[1:]),
              "machine": machine_info(), "measured_at": utc_now(),  # for bench/results_page.py
              "task": task.name, "task_digest": task.digest, "mode": "lockstep",
              "settings": {"episodes": args.episodes, "expert_frac": args.expert_frac, "seed": args.seed,
                           "train_seed": 0, "eval_episodes": args.eval_episodes,
                           "eval_seeds": [HELD_OUT, HELD_OUT + args.eval_episodes - 1]},
              "learners": {}}
    if args.resume:
        if not (args.keep and (args.keep / "raw.db3").exists() and args.out.exists()):
            print("pusher7_ros: --resume needs --keep DIR with DIR/raw.db3 and an existing --out", file=sys.stderr)
            return 2
        earlier = json.loads(args.out.read_text())
        result["commands"] = earlier.get("commands", [earlier["command"]]) + [result.pop("command")]
        result["recording"], result["learners"] = earlier["recording"], earlier["learners"]
    t_start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="pusher7_ros_") as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        raw, dataset = work / "raw.db3", work / "dataset.db3"
        for stale in (dataset,) if args.resume else (raw, dataset):
            stale.unlink(missing_ok=True)
        if not args.resume:
            result["recording"] = record(task, task_arg, args.episodes, args.expert_frac, args.seed, raw, work,
                                         args.pace_s)
            print(f"recorded {result['recording']}", flush=True)
        assert "/pusher/transition" not in result["recording"]["bag_topics"], result["recording"]["bag_topics"]
        assert cli(["dataset", "--from-topics", task_arg, str(raw), str(dataset), "--report", str(work / "join.json")]) == 0
        data = read_transitions(dataset)
        result["dataset"] = {"command": f"offline-rl dataset --from-topics {task_arg} RAW.db3 DATASET.db3",
                             "join": json.loads((work / "join.json").read_text()),
                             **same_rows(data, collect_transitions(args.episodes, args.expert_frac, args.seed, task=task))}
        print(f"dataset {result['dataset']['rows_from_topics']} rows; in process "
              f"{result['dataset']['rows_in_process']}: {result['dataset']['rows_equal_per_field']}", flush=True)
        seeds = range(HELD_OUT, HELD_OUT + args.eval_episodes)
        expert = evaluate_policy(None, args.eval_episodes, HELD_OUT, task=task)
        result["expert_in_process"] = rate(expert["successes"], args.eval_episodes)
        write_json_atomic(args.out, result)
        for algo in args.algos:
            run_dir = work / algo
            t0 = time.monotonic()
            steps = [] if algo == "auto" or args.steps is None else ["--steps", str(args.steps)]
            if algo == "auto" and args.auto_budget_s is not None:
                steps = ["--budget-s", str(args.auto_budget_s)]
            assert cli(["train", "--bag", str(dataset), "--algo", algo, "--seed", "0", *steps, "--eval-episodes", "0",
                        "--out", str(run_dir)]) == 0
            train_s = time.monotonic() - t0
            metrics = json.loads((run_dir / "metrics.json").read_text())
            policy = load_policy(run_dir / "policy.pt", task)
            local = rollout_task(task, policy.act, seeds)
            over_ros = serve(task, task_arg, run_dir / "policy.pt", args.eval_episodes, work, algo)
            agree = over_ros["success"] == local.success
            row = {"trained": {"algorithm": metrics.get("algorithm", algo), "steps": metrics.get("steps"),
                               "plan": metrics.get("plan"), "wall_s": round(train_s, 1)},
                   "in_process": rate(local.successes, args.eval_episodes),
                   "over_ros": rate(int(over_ros["success"].sum()), args.eval_episodes),
                   "over_ros_sim_summary": over_ros["sim_summary"],
                   "in_process_mean_final_dist": round(float(local.final_dist.mean()), 6),
                   "episodes_agreeing": int(agree.sum()), "outcomes_identical": bool(agree.all()),
                   "over_ros_wall_s": over_ros["wall_s"]}
            result["learners"][algo] = row
            print(f"{algo}: in process {row['in_process']}, over ROS {row['over_ros']}, "
                  f"{row['episodes_agreeing']}/{args.eval_episodes} episodes agree", flush=True)
            write_json_atomic(args.out, result)
    result["wall_s"] = round(time.monotonic() - t_start, 1)
    write_json_atomic(args.out, result)
    print(json.dumps({k: v for k, v in result.items() if k in ("learners", "expert_in_process")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
