"""rosbag2 datasets: the bag is the dataset.

- ``read_transitions(path)`` / ``write_transitions(path, transitions, storage=None)``: the
  ``/pusher/transition`` topic of a bag as Transitions, and back.
- ``BagWriter``: crash-safe streaming writer of already-serialized messages (the recorder
  node): at most the last flush interval is lost if its process is killed; splits files.
- ``repair_bag(path)``: ``offline-rl bag repair``: makes a bag cut off by a kill whole again.
- ``bag_info(path)``: ``ros2 bag info`` plus a dataset summary, for any rosbag2 bag.
- ``encode_transition_rows`` / ``decode_transition_payloads``: vectorised CDR of
  std_msgs/Float32MultiArray transitions; ``transition_ends_episode`` reads one's done flags.

Paths: ``x.db3`` / ``x.mcap`` is a single self-describing storage file, any other path a bag
directory with metadata.yaml (see ``paths``).
"""

from .cdr import (
    TRANSITION_CDR_HEADER, TRANSITION_MESSAGE_SIZE, TRANSITION_MSGTYPE, TRANSITION_TOPIC, TransitionDecodeError,
    decode_transition_payloads, encode_transition_rows, transition_ends_episode, transition_layout_msg_fields,
)
from .info import BagInfo, bag_info
from .reader import open_bag, read_transition_rows, read_transitions, topic_payloads
from .metadata import typestore
from .recording import BagWriter
from .repair import repair_bag
from .writer import TRANSITION_PERIOD_NS, TRANSITION_START_NS, write_transitions

__all__ = [
    "TRANSITION_CDR_HEADER",
    "TRANSITION_MESSAGE_SIZE",
    "TRANSITION_MSGTYPE",
    "TRANSITION_PERIOD_NS",
    "TRANSITION_START_NS",
    "TRANSITION_TOPIC",
    "BagInfo",
    "BagWriter",
    "TransitionDecodeError",
    "bag_info",
    "decode_transition_payloads",
    "encode_transition_rows",
    "open_bag",
    "read_transition_rows",
    "read_transitions",
    "repair_bag",
    "topic_payloads",
    "transition_ends_episode",
    "transition_layout_msg_fields",
    "typestore",
    "write_transitions",
]
