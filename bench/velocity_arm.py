"""The third arm (issue 23): offline RL against BC on an N-joint velocity-controlled arm nobody
modelled, learnt from its `ros2 bag record`-style log with nothing but a task file.

For each N: 200 episodes of tests/velocity_arm.py's arm (30 % by its noisy P-controller,
the rest uniform random, reset seeds 0..199) written as the bag a recorder leaves, then per
learner ``offline-rl train --task FILE --from-topics --deterministic`` (seed 0) and 100
closed-loop rollouts of the same numpy arm on the held-out resets (1000000 + e), with
Wilson intervals and the Newcombe interval of each learner's difference to BC.

    flock /tmp/pusher-cpu.lock .venv/bin/python bench/velocity_arm.py --joints 3 7 --steps 3000
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

import velocity_arm as va  # noqa: E402

from offline_rl_core.commands.cli import main as cli  # noqa: E402
from offline_rl_core.common.atomic import write_json_atomic  # noqa: E402
from offline_rl_core.benchmarks.harness import machine_info, utc_now  # noqa: E402
from offline_rl_core.common.machine import cpu_model_and_flags  # noqa: E402
from offline_rl_core.evaluation.stats import newcombe_diff_ci, wilson_ci  # noqa: E402
from offline_rl_core.serving.checkpoint import load_checkpoint  # noqa: E402
from offline_rl_core.serving.policy import LoadedPolicy  # noqa: E402
from offline_rl_core.task.spec import load_task  # noqa: E402

OUT = REPO / "bench" / "velocity_arm.json"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--joints", type=int, nargs="+", default=[3])
    parser.add_argument("--algos", nargs="+", default=["awac", "iql", "bc"])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    model, flags = cpu_model_and_flags()
    result = {"command": " ".join(["bench/velocity_arm.py", *sys.argv[1:]]),
              "machine": machine_info(), "measured_at": utc_now(),  # for bench/results_page.py
              "cpu": {"model": model, "flags": sorted(f for f in flags if f in ("avx2", "avx512f", "avx512_bf16",
                                                                                  "amx_tile"))},
              "settings": {"episodes": args.episodes, "expert_frac": 0.3, "steps": args.steps, "seed": 0,
                           "eval_episodes": 100, "eval_seed": va.HELD_OUT_SEED, "max_steps": va.MAX_STEPS,
                           "success_within": va.SUCCESS_WITHIN},
              "arms": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.joints:
            d = Path(tmp) / f"arm{n}"
            d.mkdir()
            task_file = d / "task.yaml"
            task_file.write_text(va.task_yaml(n))
            task = load_task(task_file)
            va.record_bag(d / "robot.db3", task, n, args.episodes, 0.3, 0)
            arm = {}
            for algo in args.algos:
                t0 = time.monotonic()
                assert cli(["train", "--task", str(task_file), "--from-topics", "--bag", str(d / "robot.db3"),
                            "--algo", algo, "--steps", str(args.steps), "--deterministic", "--eval-episodes", "0",
                            "--out", str(d / algo)]) == 0
                policy = LoadedPolicy(load_checkpoint(d / algo / "policy.pt"))
                k = int(va.rollouts(task, policy.act, n, 100).sum())
                arm[algo] = {"successes": k, "episodes": 100, "success": k / 100,
                             "wilson": [round(v, 4) for v in wilson_ci(k, 100)], "wall_s": round(time.monotonic() - t0, 1)}
                print(f"{n} joints {algo}: {k}/100", flush=True)
            if "bc" in arm:
                for algo in arm:
                    if algo != "bc":
                        lo, hi = newcombe_diff_ci(arm[algo]["successes"], 100, arm["bc"]["successes"], 100)
                        arm[algo]["minus_bc_newcombe"] = [round(lo, 4), round(hi, 4)]
            expert = va.rollouts(task, lambda obs, n=n, task=task: _expert(task, n, obs), n, 100)
            arm["expert_without_noise"] = {"successes": int(expert.sum()), "episodes": 100}
            result["arms"][str(n)] = arm
            write_json_atomic(args.out, result)
    print(json.dumps(result, indent=2))
    return 0


def _expert(task, n: int, obs):
    """The P-controller on the observation's goal - joints (state order), in the controller's order."""
    import numpy as np

    diff = obs[:, 2 * n: 3 * n]
    action = np.clip(va.EXPERT_GAIN * diff / va.V_MAX, -1.0, 1.0)
    return action[:, [task.state.joints.index(j) for j in task.command.joints]]


if __name__ == "__main__":
    sys.exit(main())
