"""rosbag2 datasets: the bag is the dataset.

- ``read_transitions(path)`` / ``write_transitions(path, transitions, storage=None)``: the
  ``/pusher/transition`` topic of a bag as Transitions, and back.
- ``BagWriter``: crash-safe streaming writer of already-serialized messages (the recorder
  node): at most the last flush interval is lost if its process is killed; splits files.
- ``repair_bag(path)``: ``offline-rl bag repair``: makes a bag cut off by a kill whole again.
- ``bag_info(path)``: ``ros2 bag info`` plus a dataset summary, for any rosbag2 bag.
- ``encode_transition_rows`` / ``decode_transitions``: vectorised CDR of
  std_msgs/Float32MultiArray transitions; ``transition_ends_episode`` reads one's done flags.

Paths: ``x.db3`` / ``x.mcap`` is a single self-describing storage file, any other path a bag
directory with metadata.yaml (see ``paths``).
"""

from __future__ import annotations

import importlib

# public name -> the module that defines it; loaded on first use, so a node that needs
# only the CDR codec (the sim) does not load the readers, writers and their storages
_EXPORTS = {
    "BagInfo": "info",
    "BagWriter": "recording",
    "TRANSITION_CDR_HEADER": "cdr",
    "TRANSITION_MESSAGE_SIZE": "cdr",
    "TRANSITION_MSGTYPE": "cdr",
    "TRANSITION_PERIOD_NS": "writer",
    "TRANSITION_START_NS": "writer",
    "TRANSITION_TOPIC": "cdr",
    "TransitionDecodeError": "cdr",
    "bag_info": "info",
    "decode_transition_payloads": "cdr",
    "decode_transitions": "cdr",
    "cdr_header": "cdr",
    "message_size": "cdr",
    "encode_transition_rows": "cdr",
    "open_bag": "reader",
    "read_transition_rows": "reader",
    "read_transitions": "reader",
    "repair_bag": "repair",
    "topic_payloads": "reader",
    "transition_ends_episode": "cdr",
    "transition_layout_msg_fields": "cdr",
    "typestore": "metadata",
    "write_transitions": "writer",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
