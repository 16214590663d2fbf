"""`offline-rl export-onnx`: the policy as ONNX (input `obs`, output `action`), verified."""

from __future__ import annotations

import argparse

from ..serving.onnx_export import export_onnx, verify_onnx
from ..common.output_paths import check_output_file
from ..serving.policy import load_policy


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export-onnx",
        help="export a checkpoint's policy to ONNX",
        description="Export the policy of a checkpoint to ONNX (input 'obs' [batch, 8], output 'action' "
        "[batch, 2]) and check with onnxruntime that it matches the checkpoint to 1e-5.",
    )
    p.add_argument("--checkpoint", required=True, help="policy checkpoint (.pt, or a directory holding policy.pt, such as a train --out DIR)")
    p.add_argument("--out", required=True, help="where to write the .onnx file")
    p.add_argument("--no-verify", action="store_true", help="skip the onnxruntime comparison")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_output_file(args.out, "--out")
    policy = load_policy(args.checkpoint)
    out = export_onnx(policy, args.out)
    print(f"wrote {out} (input 'obs' [batch, {policy.obs_dim}] -> output 'action' [batch, {policy.act_dim}])")
    if not args.no_verify:
        worst = verify_onnx(policy, out)
        print(f"verified with onnxruntime: max |onnx - checkpoint| = {worst:.2e} (<= 1e-05)")
    return 0
