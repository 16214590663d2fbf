"""``ros2 run trainer node``: ``offline-rl train`` as a ROS 2 node.

Same settings and outputs as ``offline-rl train`` (``--bag PATH [--bag ...] --algo ...
--steps N --seed S --out DIR``): ``DIR/policy.pt``, ``DIR/metrics.json`` and the training
curve. Every flag is also a read-only ROS parameter of the same name with dashes as
underscores (``-p algo:=awac -p bag:=[mix.db3]``, a params file, a launch file); a flag
given on the command line wins. Progress goes to the console and to ``~/progress``
(``/trainer/progress``) as ``std_msgs/String`` holding one JSON object per report:

  {"step": 400, "total": 8000, "elapsed_s": 1.9, "steps_per_s": 210.5,
   "scalars": {"critic_loss": 0.12, ...}, "done": false}

and a last one with ``"done": true, "out": DIR, "checkpoint": DIR/policy.pt``. The same
reports reach ``/diagnostics`` at most once a second (OK, "training awac: step 400 of 8000",
the step, rate and losses as key-values), the last one latched (transient local) for a
monitor that joins late, as the progress topic's are.
Exits 0 once the checkpoint is written, 2 on a bad bag or setting (one line), 130 when
interrupted (Ctrl-C or SIGTERM) before the checkpoint is written.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import String

from offline_rl_core.common.errors import UserError
from offline_rl_core.common.interrupts import interrupt_received
from offline_rl_core.nodes.diagnostics import StatusDiagnosis
from offline_rl_core.runs.training_run import (
    add_train_arguments, console_progress, run_training_from_args, summary_line,
)
from pusher_common.diagnostics import NodeDiagnostics
from pusher_common.node_main import run_node
from pusher_common.params import Settings, params_from_parser

# Transient local: a monitor that starts late still gets the latest reports (and "done").
PROGRESS_QOS = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL)
LATEST_DIAGNOSIS_QOS = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def train_params():
    """``offline-rl train``'s flags as parameters: fixed for the run, so read-only."""
    parser = argparse.ArgumentParser(add_help=False)
    add_train_arguments(parser)
    return params_from_parser(parser, read_only=True)


PARAMS = train_params()


class Trainer(Node):
    def __init__(self, overrides=()):
        super().__init__("trainer", parameter_overrides=list(overrides))
        self.settings = Settings(self, PARAMS)
        if not self.settings.bag:
            raise UserError("no bag given: pass --bag PATH (repeat for several) or -p bag:=[PATH, ...]")
        self.progress_pub = self.create_publisher(String, "~/progress", PROGRESS_QOS)
        self.console = console_progress()
        # the training loop holds the main thread (no executor): reports go out as they come,
        # at most once a second
        algo = self.settings.algo
        # its last entry latched too: a run of a few seconds can end before a monitor has matched
        self.diagnostics = NodeDiagnostics(self, status=dict, period_s=None, qos=LATEST_DIAGNOSIS_QOS,
                                           diagnosis=StatusDiagnosis(
                                               idle=lambda st: f"training {algo}: step {st['step']} of {st['total']}"))
        self.diagnosed_at = -float("inf")

    def report(self, p) -> None:
        if interrupt_received():  # a Ctrl-C during set-up whose exception a library swallowed
            raise KeyboardInterrupt
        self.console(p)
        report = {
            "step": int(p.step),
            "total": int(p.total),
            "elapsed_s": round(float(p.elapsed_s), 3),
            "steps_per_s": round(p.step / p.elapsed_s, 1) if p.elapsed_s > 0 else 0.0,
            "scalars": {k: float(v) for k, v in p.scalars.items()},
            "done": False,
        }
        self.publish(report)
        if time.monotonic() - self.diagnosed_at >= 1.0 or p.step >= p.total:
            self.diagnosed_at = time.monotonic()
            self.diagnostics.publish({k: v for k, v in report.items() if k != "done"})

    def publish(self, report: dict) -> None:
        self.progress_pub.publish(String(data=json.dumps(report)))

    def run(self) -> int:
        args = argparse.Namespace(**self.settings.as_dict())
        try:
            out = run_training_from_args(args, progress=self.report)
        except (KeyboardInterrupt, Exception) as exc:
            # a Ctrl-C that lands in an import's C code can come out as another error
            if not (isinstance(exc, KeyboardInterrupt) or interrupt_received()):
                raise
            print("trainer: interrupted; no checkpoint written", file=sys.stderr)
            return 130
        self.publish({"done": True, "out": str(out), "checkpoint": str(out / "policy.pt")})
        # a run of a second or two can end before a reader the graph already lists has matched
        # this writer: give those a second to match, then the matched readers get the last reports
        deadline = time.monotonic() + 1.0
        for pub in (self.progress_pub, self.diagnostics.publisher):
            while pub.get_subscription_count() < self.count_subscribers(pub.topic_name) and time.monotonic() < deadline:
                time.sleep(0.02)
            pub.wait_for_all_acked(rclpy.duration.Duration(seconds=1.0))
        print(summary_line(out))
        return 0


def main(argv: list[str] | None = None) -> int:
    return run_node(Trainer, prog="trainer", flags=PARAMS, argv=argv, runs_in_main=True,
                    description="Train an offline RL policy from rosbag2 bags (the options of `offline-rl train`).")


if __name__ == "__main__":
    sys.exit(main())
