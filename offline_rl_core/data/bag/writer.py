"""Writing whole datasets of transitions as rosbag2 bags (``offline-rl collect``).

Written through rosbags' rosbag2 Writer (format version 9) into a staged directory and
published atomically (see ``paths``): a bag appears complete or not at all. Message
definitions come from the ROS 2 Kilted typestore, so the bag carries the definitions and
RIHS01 hashes real ROS tools expect. Streams (the recorder) use ``recording.BagWriter``.
"""

from __future__ import annotations

import os

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Writer

from ...common.errors import UserError
from ...task.spec import TaskSpec, load_task
from ..episode_labels import LABEL_MSGTYPE, LABEL_TOPIC, encode_label_message
from ..task_record import TASK_MSGTYPE, TASK_TOPIC, encode_task_message
from ..transitions import PUSHER_LAYOUT, Layout, Transitions
from .cdr import TRANSITION_MSGTYPE, TRANSITION_TOPIC, encode_transition_blob, message_size
from .metadata import ROSBAG2_VERSION, typestore
from .paths import STORAGE_PLUGIN, StagedBag, resolve_target

# Deterministic stamps make `offline-rl collect` bit-reproducible: transition i is stamped
# TRANSITION_START_NS + i * TRANSITION_PERIOD_NS (2025-01-01T00:00:00Z, then 50 Hz).
TRANSITION_START_NS = 1_735_689_600 * 10**9
TRANSITION_PERIOD_NS = 20_000_000


def _check_rows(path, rows: np.ndarray, layout: Layout) -> None:
    if rows.ndim != 2 or rows.shape[1] != layout.width:
        raise UserError(f"{path}: expected ({layout.width},)-wide transition rows, got shape {rows.shape}")
    if rows.shape[0] == 0:
        raise UserError(f"{path}: no transitions to write")
    bad = ~np.isfinite(rows)
    if bad.any():
        column = int(np.flatnonzero(bad.any(axis=0))[0])
        raise UserError(f"{path}: {int(bad.any(axis=1).sum())} transition rows hold NaN or inf "
                        f"(first in field {layout.field_of_column(column)!r}); not writing them")


def _label_rows(rows: np.ndarray, layout: Layout, labels: dict[int, bool] | None) -> dict[int, tuple[int, bool]]:
    """{row of each labelled episode's last transition: (episode, success)}."""
    if not labels:
        return {}
    episodes = rows[:, layout.slices["episode"]].reshape(-1).astype(np.int64)
    last = {int(e): int(np.flatnonzero(episodes == e)[-1]) for e in np.unique(episodes)}
    missing = sorted(set(map(int, labels)) - set(last))
    if missing:
        raise ValueError(f"labels of episodes the transitions do not hold: {missing[:5]}")
    return {last[int(e)]: (int(e), bool(s)) for e, s in labels.items()}


def _latched_qos() -> Qos:
    """The QoS the sim offers ``/task_description`` with (as robot_description): ``ros2 bag
    play`` then offers it to late subscribers too."""
    zero = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL, zero, zero,
               QosLiveliness.AUTOMATIC, zero, False)


def write_transitions(
    path: str | os.PathLike,
    transitions: Transitions | np.ndarray,
    storage: str | None = None,
    custom_data: dict[str, str] | None = None,
    task: TaskSpec | None = None,
    labels: dict[int, bool] | None = None,
    label_episodes: bool = True,
) -> None:
    """Write transitions as a rosbag2 bag with one ``/pusher/transition`` message per row.

    ``task``: a TaskSpec the bag records on ``/task_description`` (``data.task_record``),
    except the chapter's pusher_reach, whose bags record none.

    ``path``: ``x.db3`` or ``x.mcap`` gives a single self-describing storage file, any other
    path a bag directory whose storage is ``storage`` ('sqlite3', the default, or 'mcap').
    An existing bag at ``path`` is replaced atomically; on any error it is left untouched and
    nothing half-written remains. Stamps are TRANSITION_START_NS + i * 20 ms, or with
    ``task`` i * its control period, and the bag records the task on ``/task_description``
    (data.task_record) at TRANSITION_START_NS; without one the bag is pusher_reach's.
    ``labels`` ({episode: success}): a label on ``/episode_label`` (data.episode_labels) 1 ns
    after each labelled episode's last transition, as a person's key press is recorded, naming
    its episode unless ``label_episodes`` is false (then the label is of the episode before it).
    """
    if isinstance(transitions, Transitions):
        rows, layout = transitions.to_rows(), transitions.layout
    else:
        rows, layout = np.asarray(transitions, np.float32), PUSHER_LAYOUT
    target = resolve_target(path, storage)
    _check_rows(target.path, rows, layout)
    blob = encode_transition_blob(rows, layout)
    size = message_size(layout)
    staged = StagedBag(target, overwrite=True)
    try:
        writer = Writer(staged.bag_dir, version=ROSBAG2_VERSION, storage_plugin=STORAGE_PLUGIN[target.storage])
        with writer:
            for key, value in (custom_data or {}).items():
                writer.set_custom_data(key, value)
            period_ns = TRANSITION_PERIOD_NS
            if task is not None:
                period_ns = round(task.control_period * 1e9)
            if task is not None and task.digest != load_task().digest:  # pusher_reach's bags keep their bytes
                record = writer.add_connection(TASK_TOPIC, TASK_MSGTYPE, typestore=typestore(),
                                               offered_qos_profiles=[_latched_qos()])
                writer.write(record, TRANSITION_START_NS, encode_task_message(task))
            conn = writer.add_connection(TRANSITION_TOPIC, TRANSITION_MSGTYPE, typestore=typestore())
            label_after = _label_rows(rows, layout, labels)
            label_conn = writer.add_connection(f"/{LABEL_TOPIC}", LABEL_MSGTYPE, typestore=typestore()) \
                if label_after else None
            write = writer.write
            for i, offset in enumerate(range(0, len(blob), size)):
                write(conn, TRANSITION_START_NS + i * period_ns, blob[offset : offset + size])
                if i in label_after:
                    episode, success = label_after[i]
                    write(label_conn, TRANSITION_START_NS + i * period_ns + 1,
                          encode_label_message(success, episode if label_episodes else None))
        staged.publish()
    except OSError as exc:
        raise UserError(f"{target.path}: cannot write the bag: {exc}") from exc
    finally:
        staged.discard()
