"""The online (HIL-SERL) stage in realtime: does the actor keep up while the learner trains?

The whole stage runs from ``online.launch.yaml`` in realtime (50 Hz sim, scripted corrector,
the online learner training on the other core, a passive recorder), and a DDS probe
watches it for ``realtime_seconds``: every ``/pusher/state``, every answer the policy node
reports on ``/policy/provenance`` (with the age of the weights it acted on), and every
``/learner/weights`` arrival. Figures: states left unanswered or answered more than one
tick late (target 0), the weights period against the one claimed, and the oldest weights
the actor acted on (goal: at most 1 s).

The learning curve of the stage (success against environment steps, three seeds, the
ablations) takes many minutes and is measured by ``bench/hil_online.py`` instead.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from ..task.pusher_reach import CONTROL_HZ
from .harness import BenchSettings, figure, pending
from .ros_procs import isolate, ros_missing, run_probe

REALTIME_PUBLISH_EVERY = 25  # 0.5 s of robot time: weights at most ~0.5 s old when acted on


def realtime_figures(s: BenchSettings, tmp: Path, log=print) -> list:
    import os

    from ..data.bag import read_transitions
    from ..pipelines.processes import LaunchedProcesses
    from ..learners import TrainConfig, train
    from ..serving.checkpoint import save_checkpoint
    from ..pipelines.hil_online import REALTIME_THREAD_PRIORITY
    from ..pipelines.processes import isolated_ros_env
    from ..serving.signing import make_session_keys

    bag = Path("bags/mix.db3")
    prior = tmp / "prior.pt"
    steps = 20 if s.tiny else 1000
    save_checkpoint(prior, train(read_transitions(bag), TrainConfig(algo="awac", steps=steps), seed=0).checkpoint)
    seconds = s.realtime_seconds
    episodes = int(seconds * CONTROL_HZ / 100) + 20  # the sim outlasts the probe
    arguments = {"bag": bag, "prior": prior, "checkpoint": prior, "out": tmp / "online", "mode": "realtime",
                 "paced_every": 0, "publish_every": REALTIME_PUBLISH_EVERY, "episodes": episodes,
                 "snapshot_every": 0, "learner_nice": 10, "thread_priority": REALTIME_THREAD_PRIORITY,
                 "keys": make_session_keys(tmp / "online" / "keys").signing_key.parent}
    env = isolated_ros_env(domain_id=int(os.environ["ROS_DOMAIN_ID"]))  # the probe's domain (isolate() chose it)
    with LaunchedProcesses.of("pusher_bringup", "online.launch.yaml", arguments, env, tmp / "logs") as launched:
        launched.start(ready={"learner": "learning from", "policy": "serving", "recorder": "recording"}, timeout=120)
        trace = run_probe(["online-actor", seconds], timeout=seconds + 120)
    states = {stamp: t for stamp, t in trace["states"]}
    answers = {}
    for stamp, t, version, age in trace["answers"]:
        answers.setdefault(stamp, (t, version, age))
    period_s = 1.0 / CONTROL_HZ
    ticks = sorted(states)[1:-1]  # the first and last may straddle the window
    missed = sum(1 for st in ticks if st not in answers)
    if missed and os.environ.get("PUSHER_RL_BENCH_DEBUG"):
        first = ticks[0]
        log("  unanswered ticks: " + str([(st - first) // 20_000_000 for st in ticks if st not in answers][:60]))
    delays = np.array([answers[st][0] - states[st] for st in ticks if st in answers])
    late = int((delays > period_s).sum())
    ages = np.array([a[2] for a in answers.values() if a[2] is not None])
    arrivals = np.diff(np.array(trace["weights"]))
    claimed = REALTIME_PUBLISH_EVERY / CONTROL_HZ
    log(f"  online realtime {seconds:g}s: {len(ticks)} ticks, {missed} unanswered, {late} answered > 20 ms late "
        f"(p99 {np.percentile(delays, 99) * 1e3:.2f} ms); weights every {np.median(arrivals):.3f} s "
        f"(claimed {claimed:.2f}); oldest weights acted on {ages.max():.3f} s")
    common = {"ticks": len(ticks), "missed": missed, "late": late,
              "answer_delay_p99_ms": round(float(np.percentile(delays, 99)) * 1e3, 3),
              "answer_delay_max_ms": round(float(delays.max()) * 1e3, 3)}
    return [
        figure("online", f"online_realtime_{seconds:g}s_missed_or_late", "states", missed + late, 0,
               "every 50 Hz state answered within one tick", higher_is_better=False, target=lambda o, r, x: o == 0,
               target_text="0 unanswered or late", extra=common,
               note=f"{len(ticks)} ticks with the learner training on the other core; answer delay p99 "
                    f"{common['answer_delay_p99_ms']} ms, max {common['answer_delay_max_ms']} ms"),
        figure("online", "online_weights_period_s", "s", float(np.median(arrivals)), claimed,
               f"publish_every {REALTIME_PUBLISH_EVERY} at 50 Hz", higher_is_better=False,
               target=lambda o, r, x: o <= 1.1 * r, target_text="within 10 % of the claimed period",
               extra={"versions": len(trace["weights"]), "max_gap_s": round(float(arrivals.max()), 3)},
               note=f"{len(trace['weights'])} versions; longest gap {arrivals.max():.3f} s"),
        figure("online", "online_weights_age_max_s", "s", float(ages.max()), 4.0, "LeRobot's weights push (~4 s)",
               higher_is_better=False, target=lambda o, r, x: o <= 1.0, target_text="<= 1 s",
               extra={"age_p50_s": round(float(np.median(ages)), 3)},
               note=f"age of the weights behind each action (since the learner cut them): median {np.median(ages):.3f} s"),
    ]


def run(s: BenchSettings, log=print) -> list:
    names = [f"online_realtime_{s.realtime_seconds:g}s_missed_or_late", "online_weights_period_s",
             "online_weights_age_max_s"]
    why = ros_missing()
    if why:
        return [pending("online", n, "", "", why) for n in names]
    isolate()
    with tempfile.TemporaryDirectory(prefix="bench_online_") as tmp:
        try:
            return realtime_figures(s, Path(tmp), log)
        except Exception as exc:  # noqa: BLE001 - a figure that failed says why, the bench goes on
            return [pending("online", n, "", "", f"failed: {type(exc).__name__}: {exc}"[:500], status="skipped")
                    for n in names]
