"""Export a trained policy to ONNX and check it against the numpy policy.

The graph maps ``obs`` (float32, [batch, obs_dim], dynamic batch) to ``action``
(float32, [batch, act_dim], tanh-squashed), the same function as ``LoadedPolicy.act``;
the sizes are the checkpoint's, whatever its task. The model's metadata names the task
(``pusher-rl.task``: the checkpoint's task layout as JSON: name, digest, one label per
observation and action value), so a runtime outside this project knows what to feed it.
torch 2.13's default (dynamo) exporter needs ``onnxscript``; the TorchScript-based
exporter (``dynamo=False``) needs only ``onnx``, so that is what we use.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import torch

from ..common.errors import UserError
from ..common.atomic import atomic_path
from .checkpoint import checkpoint_layout
from .policy import LoadedPolicy

OPSET = 17


def export_onnx(policy: LoadedPolicy, out: str | os.PathLike) -> Path:
    """Write ``policy`` as an ONNX model to ``out`` (atomically)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    module = policy.torch_module()
    example = torch.zeros(1, policy.obs_dim, dtype=torch.float32)
    with atomic_path(out, suffix=".onnx") as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the legacy exporter's deprecation notice
        torch.onnx.export(
            module,
            (example,),
            str(tmp),
            input_names=["obs"],
            output_names=["action"],
            dynamic_axes={"obs": {0: "batch"}, "action": {0: "batch"}},
            opset_version=OPSET,
            dynamo=False,
        )
        _name_the_task(tmp, checkpoint_layout(policy.checkpoint))
    return out


def _name_the_task(path, layout: dict) -> None:
    import onnx  # the exporter above needs it too

    model = onnx.load(str(path))
    entry = model.metadata_props.add()
    entry.key, entry.value = "pusher-rl.task", json.dumps(layout)
    onnx.save(model, str(path))


def verify_onnx(policy: LoadedPolicy, onnx_path: str | os.PathLike, n: int = 256, seed: int = 0, atol: float = 1e-5) -> float:
    """Max |onnxruntime - numpy act()| over ``n`` random observations (batch 1 and n).

    Raises ``UserError`` when onnxruntime is missing or the outputs differ by more
    than ``atol``.
    """
    try:
        import onnxruntime as ort
    except ImportError:
        raise UserError("onnxruntime is not installed; install the 'onnx' extra to verify the export") from None
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(seed)
    obs = rng.standard_normal((n, policy.obs_dim)).astype(np.float32)
    worst = 0.0
    for batch in (obs[:1], obs):
        (got,) = session.run(["action"], {"obs": batch})
        worst = max(worst, float(np.max(np.abs(got - policy.act(batch)))))
    if worst > atol:
        raise UserError(f"{onnx_path}: ONNX output differs from the checkpoint's policy by {worst:.3g} (> {atol:g})")
    return worst
