"""The weights message: how the online learner hands a new policy to the acting policy node.

A weights version travels as a ``std_msgs/UInt8MultiArray`` whose layout is labelled
``WEIGHTS_LABEL`` and whose bytes are a checkpoint holding only what acting needs
(``serving_part``: the task it acts on included), validated on arrival exactly as a
checkpoint file is; the policy node refuses weights of another task than its own.
"""

from __future__ import annotations

from ..common.errors import UserError
from ..common.rejections import Rejection
from .checkpoint import checkpoint_from_bytes, checkpoint_to_bytes
from ..task.spec import DEFAULT_TASK, TaskSpec
from .policy import LoadedPolicy, policy_for_task

WEIGHTS_LABEL = "pusher-rl/weights"  # the weights message's layout label: what its bytes are


def encode_weights(checkpoint: dict) -> bytes:
    """A weights version as the bytes of a ``std_msgs/UInt8MultiArray`` (a checkpoint,
    ``torch.save`` format, loaded back with ``weights_only``)."""
    return checkpoint_to_bytes(serving_part(checkpoint))


def serving_part(checkpoint: dict) -> dict:
    """What acting needs: the policy, its exploration std, dims, task and provenance."""
    keep = ("format", "version", "algorithm", "obs_dim", "act_dim", "hidden", "policy_state", "obs_mean", "obs_std",
            "exploration_log_std", "task", "weights_version", "trained_through", "updates", "seed", "cut_unix")
    return {k: checkpoint[k] for k in keep if k in checkpoint}


def decode_weights(data: bytes, source: str = "weights message") -> dict:
    return checkpoint_from_bytes(data, source)


def policy_from_weights_message(label: str, data: bytes, source: str,
                                task: TaskSpec | str = DEFAULT_TASK) -> tuple[LoadedPolicy | None, Rejection | None]:
    """The policy a weights message carries (its layout label and bytes), or (None, why not):
    weights of another task than ``task`` (the acting node's) are refused."""
    if label != WEIGHTS_LABEL:
        return None, Rejection("bad layout", f"layout label {label[:40]!r}, expected {WEIGHTS_LABEL!r}")
    try:
        return policy_for_task(decode_weights(data, source), source, task), None
    except UserError as exc:
        return None, Rejection("bad weights", str(exc))
    except Exception as exc:  # noqa: BLE001 - a validated checkpoint with odd field types; keep serving
        return None, Rejection("bad weights", f"{source}: {type(exc).__name__}: {str(exc)[:120]}")
