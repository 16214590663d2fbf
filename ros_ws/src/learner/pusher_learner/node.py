"""The online learner of the HIL-SERL stage.

``ros2 run learner node --bag bags/mix.db3 --prior runs/demo/awac/policy.pt``. Subscribes
to the live ``pusher/transition`` stream (every source: the policy's steps and a person's
takeovers; with ``-p actors:=[/arm1, /arm2]`` that of each actor namespace, counted apart),
keeps it in an online buffer beside the offline bag(s), trains continuously (``utd`` gradient
steps per transition, half of each batch from the offline data), and every ``publish_every``
transitions publishes a new weights version on ``~/weights`` (``std_msgs/UInt8MultiArray``,
layout label ``pusher-rl/weights``: raw tensors with a JSON header, signed with the session's
private key ``signing_key``, see ``offline_rl_core.serving.weights``; reliable, transient
local, so a policy node that starts late gets the latest). The policy node acts on them
(``-p weights_topic:=/learner/weights`` with ``-p weights_key:=`` the session's public key).
``OUT/policy.pt`` always holds the latest version; ``OUT/learner_state.pt`` is a resume point
(every ``save_every`` s and at exit); ``--resume`` continues from it, reading the
transitions that arrived while it was down from ``--session-bag`` (the session's
recording). ``~/status`` (``std_msgs/String``, JSON, once a second; ``pusher_common.status``):
counts, losses, rejections by reason. A transition with a non-finite value, an action
outside [-1, 1], a value out of range or an unknown layout is dropped, counted and warned
about (throttled), never trained on; so is every transition that comes while the e-stop is
engaged (``estop``, released only by ``estop/reset``: ``pusher_common.estop``), and every
transition of an actor while that actor's own e-stop (``/arm1/estop``) is engaged. The
learner trains on the wall clock: with ``use_sim_time`` its work still runs (the sim's
clock waits for the policy, which waits for the learner's weights).

``--from-topics`` (``-p from_topics:=true``, with ``-p task:=NAME_OR_FILE``): a robot that
publishes only standard topics. The learner subscribes to the task's raw topics (its
joint states, its controller's commands and the project's action topics, the goal, the
tracked points, the reset topic) and builds the transitions live with the same join as
``offline-rl dataset`` (``offline_rl_core.data.raw_topics.LiveJoin``); its first weights
wait until the state and goal topics are heard, so a paced actor never outruns it. A task
joined by receive times (``join.stamps: receive``: commands without a header) on a sim
(``-p use_sim_time:=true``) has each message stamped by the sim time of its publication
(its source timestamp against the /clock's), as the recorder on sim time stamps the bag.
With ``-p action_labels:=true`` it also joins the scripted corrector's action labels
(``corrections/action_label``, one per state it leaves to the policy) to the states they
label: the actor's BC term imitates them there (DAgger's labels), the critic learns from the
action the arm took.

The logic lives in ``offline_rl_core.nodes.learner_service``; this node only moves messages.
"""

from __future__ import annotations

import array
import os
import sys

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock as ClockMsg
from std_msgs.msg import Float32MultiArray, MultiArrayDimension, UInt8MultiArray

from offline_rl_core.data.raw_topics.live import LiveSettings
from offline_rl_core.learners.config import TrainConfig
from offline_rl_core.learners.online import OnlineSettings
from offline_rl_core.nodes.learner_service import LearnerService, LearnerServiceConfig
from offline_rl_core.nodes.publication_clock import published_ns
from offline_rl_core.runs.loggers import DEFAULT_LOGGER, LOGGERS
from offline_rl_core.serving.signing import load_signer
from offline_rl_core.serving.weights import WEIGHTS_LABEL, encode_weights
from pusher_common.estop import EStopInput
from pusher_common.message_types import message_class
from pusher_common.node_main import run_node
from pusher_common.params import Param, Settings
from pusher_common.status import NodeStatus
from offline_rl_core.nodes.diagnostics import StatusDiagnosis, learner_checks

# Deep and reliable: in lockstep the sim publishes as fast as it is answered, and a
# transition lost here is a transition the learner never trains on.
TRANSITION_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
# Several versions kept: a policy node that falls behind still gets each one in order.
WEIGHTS_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)

_T = TrainConfig(algo="sac")
_O = OnlineSettings()
_L = LiveSettings()
DISCOVERY_PERIOD_S = 0.5  # the reset topic, whose type the task leaves open, is subscribed once seen
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
    Param("imitate_expert", _O.imitate_expert, "the actor's BC term (bc_weight) also on the offline bag's expert rows "
          "(its demonstrations), as TD3+BC keeps an actor near them", read_only=True, flag="--imitate-expert"),
    Param("critic_warmup", _O.critic_warmup, "gradient steps of the critic alone on the offline bag, with the prior's "
          "actor, before the first update (a prior without a critic)", low=0, read_only=True, flag="--critic-warmup"),
    Param("normalize_obs", _T.normalize_obs, "actor and critic learn on observations z-scored by the offline bag's "
          "statistics (fixed for the session), folded into every weights version", read_only=True,
          flag="--normalize-obs"),
    Param("lr_decay_steps", _O.lr_decay_steps, "environment steps over which the learning rates fall along a cosine "
          "to zero (the session's budget; 0: constant rates)", low=0, read_only=True, flag="--lr-decay-steps"),
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
    Param("actors", [], "namespaces of the actors (sim and policy node each) whose pusher/transition the learner "
          "trains on, e.g. [/arm1, /arm2]; none: its own namespace's", read_only=True, flag="--actors", kind=list),
    Param("from_topics", False, "build the live transitions from the task's raw topics (joint states, commands, "
          "goal) instead of pusher/transition", read_only=True, flag="--from-topics"),
    Param("action_labels", False, "raw topics: also join the corrector's action labels (corrections/action_label) "
          "to the states they label; the actor imitates them, the critic learns from the actions the arm took",
          read_only=True, flag="--action-labels"),
    Param("success", "", "raw topics: a success classifier file (offline-rl classifier train) that judges each "
          "state's success, for the reward's bonus and the episode's end, instead of the task's success distance; "
          "empty: the distance", read_only=True, flag="--success"),
    Param("end_on_success", False, "raw topics: an episode ends at its first success (terminated, the steps after it "
          "left out), as the arm's episodes end where a policy node's end_on_success classifier labels them",
          read_only=True, flag="--end-on-success"),
    Param("lateness", _L.lateness, "raw topics: seconds of stamps a silent topic (a goal sent once an episode) is "
          "taken complete behind the joint states", low=0.0, high=60.0, read_only=True, flag="--lateness"),
    Param("quiet", _L.quiet, "raw topics: seconds with nothing new, while idle, after which everything published is "
          "taken to have arrived (a lockstep arm waiting for the learner)", low=0.001, high=10.0, read_only=True,
          flag="--quiet"),
    Param("quiet_missing", _L.quiet_missing, "raw topics: seconds with nothing new, while idle, after which a state "
          "still without its command is taken to have none (a command only delayed comes within it)", low=0.001,
          high=60.0, read_only=True, flag="--quiet-missing"),
    Param("logger", DEFAULT_LOGGER, "where each weights version's losses and rates go besides progress.jsonl: "
          "tensorboard (event files in OUT), wandb (OUT/wandb) or none", choices=LOGGERS, read_only=True,
          flag="--logger"),
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
                            batch_size=s.batch_size, threads=s.threads, normalize_obs=s.normalize_obs)
        settings = OnlineSettings(utd=s.utd, offline_ratio=s.offline_ratio, publish_every=s.publish_every,
                                  capacity=s.capacity, imitate_expert=s.imitate_expert,
                                  critic_warmup=s.critic_warmup, lr_decay_steps=s.lr_decay_steps)
        self.service = LearnerService(LearnerServiceConfig(
            bags=list(s.bag), out=s.out, prior=s.prior or None, task=s.task or None, seed=s.seed,
            save_every=s.save_every, resume=s.resume, session_bag=s.session_bag or None,
            snapshot_every=s.snapshot_every, from_topics=s.from_topics, success=s.success or None,
            end_on_success=s.end_on_success,
            action_labels=s.action_labels, actors=tuple(s.actors or ()),
            live=LiveSettings(lateness=s.lateness, quiet=s.quiet, quiet_missing=s.quiet_missing),
            settings=settings, train=train,
            logger=s.logger, sim_time=bool(self.get_parameter("use_sim_time").value)),
            log=self.get_logger().info)
        self.weights_pub = self.create_publisher(UInt8MultiArray, "~/weights", WEIGHTS_QOS)
        self.status = NodeStatus(self, fields=self.service.status, counter=self.service.rejected,
                                 diagnosis=StatusDiagnosis(checks=(learner_checks,), idle=lambda st: (
                                     f"weights version {st['weights_version']}, {st['updates']} updates")))
        self.estop = EStopInput(self, latch=self.service.estop)
        self.actor_estops = [EStopInput(self, latch=latch, namespace=ns)
                             for ns, latch in self.service.actor_estops.items()]
        # topic -> (subscription, message class, callback) of each raw topic
        self.raw_subs: dict[str, tuple[object, type, object]] = {}
        self.clock_sub = None
        self.first_published = False
        # wall-clock timers, also under use_sim_time: a timer on sim time would wait for a
        # clock that waits for these weights
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        if s.from_topics:
            if self.service.publication_clock is not None:  # before the raw topics' subscriptions
                self.clock_sub = self.create_subscription(ClockMsg, "/clock", self.on_clock, QoSProfile(
                    depth=100, reliability=ReliabilityPolicy.RELIABLE), raw=True)
            self.subscribe_raw_topics()
            self.create_timer(DISCOVERY_PERIOD_S, self.subscribe_raw_topics, clock=steady)
            what = f"the raw topics of task {self.service.task.name}"
        else:
            for actor, topic in self.service.transition_topics:
                self.create_subscription(Float32MultiArray, topic, lambda raw, a=actor, t=topic: self.on_transition(
                    raw, a, t), TRANSITION_QOS, raw=True)
            what = "live transitions" + (f" of {len(s.actors)} actors ({', '.join(s.actors)})" if s.actors else "")
            self.publish_first()
        self.create_timer(0.002, self.work, clock=steady)
        self.get_logger().info(
            f"learning from {len(s.bag)} bag(s) + {what}; weights version "
            f"{self.service.weights['weights_version']} on {self.weights_pub.topic_name}; "
            f"utd {s.utd}, new weights every {s.publish_every} environment steps")

    def subscribe_raw_topics(self) -> None:
        """Subscribe the task's topics, each with its type (the reset topic's from the graph)."""
        graph = None
        for role in self.service.live.topics():
            if role.topic in self.raw_subs:
                continue
            msgtype = role.types[0] if role.types else None
            if msgtype is None:
                graph = graph if graph is not None else dict(self.get_topic_names_and_types())
                seen = graph.get(self.resolve_topic_name(role.given), [])
                msgtype = seen[0] if len(seen) == 1 else None
            msg_class = message_class(msgtype) if msgtype else None
            if msg_class is None:
                continue
            callback = self.raw_callback(role.topic, msgtype)
            sub = self.create_subscription(msg_class, role.given, callback, TRANSITION_QOS, raw=True)
            self.raw_subs[role.topic] = (sub, msg_class, callback)

    def raw_callback(self, topic: str, msgtype: str):
        def on_raw(raw: bytes, info) -> None:  # with its MessageInfo: when it was published
            self.on_raw(topic, msgtype, raw, published_ns(info))

        return on_raw

    def on_raw(self, topic: str, msgtype: str, raw: bytes, published: int | None = None) -> None:
        self.status.took(topic)
        rejection = self.service.receive_message(topic, msgtype, raw, self.get_clock().now().nanoseconds, published)
        if rejection is not None:
            self.status.warn(topic, rejection)

    def on_clock(self, raw: bytes, info) -> None:
        clock = deserialize_message(raw, ClockMsg).clock
        rejection = self.service.receive_clock(published_ns(info), clock.sec * 1_000_000_000 + clock.nanosec)
        if rejection is not None:
            self.status.warn("/clock", rejection)

    def publish_first(self) -> None:
        """Publish the first weights, once.

        At once for pusher/transition; with raw topics once the state and goal topics are
        heard (a paced actor acts on them: no step may be missed).
        """
        if not self.first_published:
            self.first_published = True
            self.publish(self.service.weights)

    def on_transition(self, raw: bytes, actor: str | None = None, topic: str = "pusher/transition") -> None:
        self.status.took(topic)
        rejection = self.service.receive(raw, actor)
        if rejection is not None:
            self.status.warn(topic, rejection)

    def take_pending(self) -> None:
        """Take every message DDS already holds for us, each /clock first.

        Called before the live join judges whether the stream fell quiet. The quiet rule
        counts the time since a message was last taken. The executor takes one message per
        subscription a turn, and a learner starved of CPU for a while (a busy machine) has
        messages waiting that it has not taken: without this it would take a stream still
        flowing for a quiet one, stamp a state by the /clock before its own and lose that
        step for good, and a lockstep session would wait for the step forever.
        """
        if self.clock_sub is not None:
            while (taken := self.clock_sub.handle.take_message(ClockMsg, True)) is not None:
                self.on_clock(*taken)
        for sub, msg_class, callback in self.raw_subs.values():
            while (taken := sub.handle.take_message(msg_class, True)) is not None:
                callback(*taken)

    def work(self) -> None:
        if self.service.live is not None:
            self.take_pending()
        if not self.first_published and self.service.live.heard_stream():
            self.publish_first()
        for weights in self.service.work(budget_s=0.02):
            self.publish(weights)

    def publish(self, weights: dict) -> None:
        msg = UInt8MultiArray(data=array.array("B", encode_weights(weights, self.signer)))
        msg.layout.dim = [MultiArrayDimension(label=WEIGHTS_LABEL, size=len(msg.data), stride=1)]
        self.weights_pub.publish(msg)

    def close(self) -> None:
        self.service.close()


def main(argv: list[str] | None = None) -> int:
    return run_node(Learner, prog="learner", flags=PARAMS, argv=argv,
                    description="The online HIL-SERL learner: fine-tune the prior from live transitions, "
                                "publish weights to the acting policy node.")


if __name__ == "__main__":
    sys.exit(main())
