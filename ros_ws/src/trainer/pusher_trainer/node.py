"""``ros2 run trainer node``: ``offline-rl train`` as a ROS 2 node.

Same flags and outputs as ``offline-rl train`` (``--bag PATH [--bag ...] --algo ...
--steps N --seed S --out DIR``): ``DIR/policy.pt``, ``DIR/metrics.json`` and the training
curve. Progress goes to the console and to ``/trainer/progress`` as ``std_msgs/String``
holding one JSON object per report:

  {"step": 400, "total": 8000, "elapsed_s": 1.9, "steps_per_s": 210.5,
   "scalars": {"critic_loss": 0.12, ...}, "done": false}

and a last one with ``"done": true, "out": DIR, "checkpoint": DIR/policy.pt``.
Exits 0 once the checkpoint is written, 2 on a bad bag or flag (one line).
"""

from __future__ import annotations

import argparse
import json
import sys

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from rclpy.utilities import remove_ros_args
from std_msgs.msg import String

from offline_rl_core.errors import UserError
from offline_rl_core.training_run import add_train_arguments, console_progress, run_training_from_args, summary_line

# Transient local: a monitor that starts late still gets the latest reports (and "done").
PROGRESS_QOS = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ros2 run trainer node",
        description="Train an offline RL policy from rosbag2 bags (the options of `offline-rl train`).",
    )
    add_train_arguments(parser)
    return parser


class Trainer(Node):
    def __init__(self):
        super().__init__("trainer")
        self.progress_pub = self.create_publisher(String, "~/progress", PROGRESS_QOS)
        self.console = console_progress()

    def report(self, p) -> None:
        self.console(p)
        self.publish(
            {
                "step": int(p.step),
                "total": int(p.total),
                "elapsed_s": round(float(p.elapsed_s), 3),
                "steps_per_s": round(p.step / p.elapsed_s, 1) if p.elapsed_s > 0 else 0.0,
                "scalars": {k: float(v) for k, v in p.scalars.items()},
                "done": False,
            }
        )

    def publish(self, report: dict) -> None:
        self.progress_pub.publish(String(data=json.dumps(report)))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv if argv is None else argv
    args = build_parser().parse_args(remove_ros_args(argv)[1:])
    rclpy.init(args=argv)
    node = None
    try:
        node = Trainer()
        out = run_training_from_args(args, progress=node.report)
        node.publish({"done": True, "out": str(out), "checkpoint": str(out / "policy.pt")})
        node.progress_pub.wait_for_all_acked(rclpy.duration.Duration(seconds=1.0))
        print(summary_line(out))
        return 0
    except UserError as exc:
        print(f"trainer: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("trainer: interrupted; no checkpoint written", file=sys.stderr)
        return 130
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
