"""Which task a recording is of: the ``/task_description`` topic.

Like ``robot_description``, the sim publishes its task (std_msgs/String, transient local:
the task file's content as JSON) so that a recorder, ``ros2 bag record`` included, keeps it
in the bag; ``offline-rl collect`` writes it too. A bag that records its task needs no
``--task``; a bag without one is of the chapter's ``pusher_reach`` (every bag made before
tasks existed, and the shipped ``bags/mix.db3``, whose bytes stay the chapter's).
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path

from ..common.errors import UserError
from ..task.spec import TaskSpec, builtin_tasks, load_task, task_from_dict

TASK_TOPIC = "/task_description"
TASK_MSGTYPE = "std_msgs/msg/String"


def task_json(task: TaskSpec) -> str:
    return json.dumps(task.describe(), sort_keys=True)


def encode_task_message(task: TaskSpec) -> bytes:
    """The CDR bytes of the std_msgs/String that describes ``task``."""
    text = task_json(task).encode() + b"\x00"
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(text)) + text


def decode_task_message(payload: bytes, source: str) -> TaskSpec:
    try:
        (n,) = struct.unpack_from("<I" if payload[1] == 1 else ">I", payload, 4)
        doc = json.loads(bytes(payload[8: 8 + n]).rstrip(b"\x00").decode())
    except (struct.error, ValueError, UnicodeDecodeError, IndexError) as exc:
        raise UserError(f"{source}: {TASK_TOPIC} does not hold a task description ({exc})") from None
    task = task_from_dict(doc, Path(f"{source}:{TASK_TOPIC}"))
    # a built-in task is the built-in file, whose neighbours (a sim's model file) are here
    return next((b for b in map(load_task, builtin_tasks()) if b.digest == task.digest), task)


def recorded_task(path: str | os.PathLike) -> TaskSpec | None:
    """The task a bag records (its last ``/task_description``), or None when it records none."""
    from .bag.reader import open_bag, topic_payloads

    with open_bag(path) as reader:
        topics = [c.topic for c in reader.connections if c.topic.endswith(TASK_TOPIC)]
        if not topics:
            return None
        payloads = topic_payloads(reader, topics[0])
    return decode_task_message(payloads[-1], str(path)) if payloads else None


def task_of_bag(path: str | os.PathLike, given: str | os.PathLike | TaskSpec | None = None) -> TaskSpec:
    """The task to read a bag as: the one given (which must agree with what the bag records),
    else the recorded one, else pusher_reach."""
    recorded = recorded_task(path)
    if given is None:
        return recorded if recorded is not None else load_task()
    task = load_task(given)
    if recorded is not None and recorded.digest != task.digest:
        raise UserError(f"{path}: the bag records task {recorded.name} (digest {recorded.digest}); "
                        f"--task gives {task.name} (digest {task.digest})")
    return task


def chosen_task(task: str | os.PathLike | TaskSpec | None, from_topics: str | os.PathLike | None
                ) -> str | os.PathLike | TaskSpec | None:
    """The task of ``--task`` and ``--from-topics TASK`` (which must be the same task when both
    are given: a name and the path of the same file agree)."""
    if task is None or from_topics is None:
        return task if task is not None else from_topics
    if load_task(task).digest != load_task(from_topics).digest:
        name = task.name if isinstance(task, TaskSpec) else task
        raise UserError(f"--task {name} and --from-topics {from_topics} name different tasks; give one")
    return task


def check_layout_fits(path: str | os.PathLike, obs_dim: int, act_dim: int, task: TaskSpec) -> None:
    """Refuse (one line naming the bag and both layouts) transitions whose sizes are not the task's."""
    if (obs_dim, act_dim) != (task.obs_dim, task.act_dim):
        raise UserError(f"{path}: its transitions have obs {obs_dim}, action {act_dim}; task {task.name} "
                        f"({task.source_file()}, digest {task.digest}) has obs {task.obs_dim}, action {task.act_dim}")
