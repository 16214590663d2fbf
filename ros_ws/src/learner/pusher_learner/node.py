"""The online learner of the HIL-SERL stage.

``ros2 run learner node --bag bags/mix.db3 --prior runs/demo/awac/policy.pt``. Subscribes
to the live ``pusher/transition`` stream (every source: the policy's steps and a person's
takeovers), keeps it in an online buffer beside the offline bag(s), trains
continuously (``utd`` gradient steps per transition, half of each batch from the offline
data), and every ``publish_every`` transitions publishes a new weights version on
``~/weights`` (``std_msgs/UInt8MultiArray``, layout label ``pusher-rl/weights``: raw tensors
with a JSON header, signed with the session's private key ``signing_key``, see
``offline_rl_core.serving.weights``; reliable, transient local, so a policy node that starts
late gets the latest). The policy node acts on them (``-p weights_topic:=/learner/weights``
with ``-p weights_key:=`` the session's public key).
``OUT/policy.pt`` always holds the latest version; ``OUT/learner_state.pt`` is a resume point
(every ``save_every`` s and at exit); ``--resume`` continues from it, reading the
transitions that arrived while it was down from ``--session-bag`` (the session's
recording). ``~/status`` (``std_msgs/String``, JSON, once a second; ``pusher_common.status``):
counts, losses, rejections by reason. A transition with a non-finite value, an action
outside [-1, 1], a value out of range or an unknown layout is dropped, counted and warned
about (throttled), never trained on. The learner trains on the wall clock: with
``use_sim_time`` its work still runs (the sim's clock waits for the policy, which waits
for the learner's weights).

The logic lives in ``offline_rl_core.nodes.learner_service``; this node only moves messages.
"""

from __future__ import annotations

import array
import os
import sys

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float32MultiArray, MultiArrayDimension, UInt8MultiArray

from offline_rl_core.learners.config import TrainConfig
from offline_rl_core.learners.online import OnlineSettings
from offline_rl_core.nodes.learner_service import LearnerService, LearnerServiceConfig
from offline_rl_core.serving.signing import load_signer
from offline_rl_core.serving.weights import WEIGHTS_LABEL, encode_weights
from pusher_common.node_main import run_node
from pusher_common.params import Param, Settings
from pusher_common.status import NodeStatus

# Deep and reliable: in lockstep the sim publishes as fast as it is answered, and a
# transition lost here is a transition the learner never trains on.
TRANSITION_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
# Several versions kept: a policy node that falls behind still gets each one in order.
WEIGHTS_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)

_T = TrainConfig(algo="sac")
_O = OnlineSettings()
PARAMS = [
    Param("bag", [], "offline bag(s) sampled beside the live data (repeat the flag)", read_only=True, flag="--bag",
          kind=list),
    Param("prior", None, "checkpoint that initialises the actor (and the critic, when it holds one); "
          "unset: from scratch", read_only=True, flag="--prior", kind=str),
    Param("task", "", "the task (a built-in name or a task file), recorded in every weights version; empty: the "
          "prior's, else the one the bag records, else pusher_reach", read_only=True, flag="--task"),
    Param("out", "runs/online", "directory for policy.pt, learner_state.pt and progress.jsonl", read_only=True,
          flag="--out"),
    Param("signing_key", "", "the session's private key file (weights.key, from offline-rl weights-key; readable "
          "by this user alone): every weights message is signed with it", read_only=True, flag="--signing-key"),
    Param("seed", 0, "seed of initialisation, batches and the policy's noise", read_only=True, flag="--seed"),
    Param("utd", _O.utd, "gradient steps per live transition", low=1, high=64, read_only=True, flag="--utd"),
    Param("offline_ratio", _O.offline_ratio, "share of each batch drawn from the offline bag(s)", low=0.0, high=1.0,
          read_only=True, flag="--offline-ratio"),
    Param("publish_every", _O.publish_every, "live transitions between weights versions (50 = 1 s at 50 Hz)", low=1,
          read_only=True, flag="--publish-every"),
    Param("capacity", _O.capacity, "live transitions the online buffer holds", low=1, read_only=True,
          flag="--capacity"),
    Param("alpha", _T.alpha, "entropy weight of the SAC objective", low=1e-8, read_only=True, flag="--alpha"),
    Param("bc_weight", _T.bc_weight, "weight of the squared error to a person's actions", low=0.0, read_only=True,
          flag="--bc-weight"),
    Param("init_log_std", _T.init_log_std, "initial log-std of the exploring policy", low=-5.0, high=1.0,
          read_only=True, flag="--init-log-std"),
    Param("lr", _T.lr, "Adam learning rate", low=1e-8, high=1.0, read_only=True, flag="--lr"),
    Param("batch_size", _T.batch_size, "batch size", low=1, read_only=True, flag="--batch-size"),
    Param("threads", 1, "CPU threads a training step runs on (1: the other cores stay with the nodes that act)", low=1,
          read_only=True, flag="--threads"),
    Param("nice", 0, "raise the learner's niceness by this much, so a realtime actor on the same machine is "
          "scheduled first (0-19)", low=0, high=19, read_only=True, flag="--nice"),
    Param("save_every", 2.0, "seconds between resume points (learner_state.pt)", low=0.1, read_only=True,
          flag="--save-every"),
    Param("snapshot_every", 0, "live transitions between kept weights snapshots (OUT/snapshots; 0: none)", low=0,
          read_only=True, flag="--snapshot-every"),
    Param("resume", False, "continue from OUT/learner_state.pt", read_only=True, flag="--resume"),
    Param("session_bag", None, "the session's recording, to read back transitions missed while down (with --resume)",
          read_only=True, flag="--session-bag", kind=str),
]


class Learner(Node):
    def __init__(self, overrides=()):
        super().__init__("learner", parameter_overrides=list(overrides))
        s = Settings(self, PARAMS)
        from offline_rl_core.common.errors import UserError

        if s.nice:
            os.nice(s.nice)  # training yields the CPU to the nodes that answer the arm in time
        if not s.bag:
            raise UserError("no offline bag given: pass --bag PATH (repeat for several) or -p bag:=[PATH, ...]")
        if not s.signing_key:
            raise UserError("no signing key given: pass --signing-key PATH (offline-rl weights-key DIR makes "
                            "DIR/weights.key for the learner and DIR/weights.pub for the policy node)")
        self.signer = load_signer(s.signing_key)
        train = TrainConfig(algo="sac", alpha=s.alpha, bc_weight=s.bc_weight, init_log_std=s.init_log_std, lr=s.lr,
                            batch_size=s.batch_size, threads=s.threads)
        settings = OnlineSettings(utd=s.utd, offline_ratio=s.offline_ratio, publish_every=s.publish_every,
                                  capacity=s.capacity)
        self.service = LearnerService(LearnerServiceConfig(
            bags=list(s.bag), out=s.out, prior=s.prior or None, task=s.task or None, seed=s.seed,
            save_every=s.save_every, resume=s.resume,
            session_bag=s.session_bag or None, snapshot_every=s.snapshot_every, settings=settings, train=train),
            log=self.get_logger().info)
        self.weights_pub = self.create_publisher(UInt8MultiArray, "~/weights", WEIGHTS_QOS)
        self.status = NodeStatus(self, fields=self.service.status, counter=self.service.rejected)
        self.create_subscription(Float32MultiArray, "pusher/transition", self.on_transition, TRANSITION_QOS,
                                 raw=True)
        # wall-clock work, also under use_sim_time: a timer on sim time would wait for a
        # clock that waits for these weights
        self.create_timer(0.002, self.work, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.publish(self.service.weights)
        self.get_logger().info(
            f"learning from {len(s.bag)} bag(s) + live transitions; weights version "
            f"{self.service.weights['weights_version']} on {self.weights_pub.topic_name}; "
            f"utd {s.utd}, new weights every {s.publish_every} transitions")

    def on_transition(self, raw: bytes) -> None:
        self.status.took("pusher/transition")
        rejection = self.service.receive(raw)
        if rejection is not None:
            self.status.warn("pusher/transition", rejection)

    def work(self) -> None:
        for weights in self.service.work(budget_s=0.02):
            self.publish(weights)

    def publish(self, weights: dict) -> None:
        msg = UInt8MultiArray(data=array.array("B", encode_weights(weights, self.signer)))
        msg.layout.dim = [MultiArrayDimension(label=WEIGHTS_LABEL, size=len(msg.data), stride=1)]
        self.weights_pub.publish(msg)

    def close(self) -> None:
        self.service.save()


def main(argv: list[str] | None = None) -> int:
    return run_node(Learner, prog="learner", flags=PARAMS, argv=argv,
                    description="The online HIL-SERL learner: fine-tune the prior from live transitions, "
                                "publish weights to the acting policy node.")


if __name__ == "__main__":
    sys.exit(main())
