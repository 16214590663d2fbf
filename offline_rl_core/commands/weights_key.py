"""`offline-rl weights-key DIR`: a new key pair for one online session's weights messages."""

from __future__ import annotations

import argparse

from ..common.output_paths import check_output_dir
from ..serving.signing import make_session_keys


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "weights-key",
        help="make a session's key pair: the learner signs its weights, the policy node takes only those",
        description="Write DIR/weights.key (Ed25519 private key, mode 0600: the learner's signing_key) and "
        "DIR/weights.pub (its public key: the policy node's weights_key). A pair already in DIR is replaced: "
        "make one per session, so weights of another session are never taken.",
    )
    p.add_argument("dir", help="directory for the pair (made 0700 if new)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    keys = make_session_keys(check_output_dir(args.dir, "DIR"))
    print(f"wrote {keys.signing_key} (learner: -p signing_key:=...) and {keys.public_key} "
          f"(policy node: -p weights_key:=...)")
    return 0
