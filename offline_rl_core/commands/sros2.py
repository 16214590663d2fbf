"""`offline-rl sros2 --keystore DIR`: least-privilege SROS2 permissions for the project's nodes."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..common.atomic import write_text_atomic
from ..common.errors import UserError
from ..common.output_paths import check_output_dir
from ..nodes.sros2_policy import NODE_GRAPH, enclave_path, permissions_xml, policy_xml, xml_text


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sros2",
        help="write SROS2 permissions for the nodes (a policy for ros2 security, and each enclave's permissions)",
        description="Write DIR/policy.xml, an SROS2 policy giving each node (enclave /pusher_rl/NODE) only the "
        "topics and services it uses, and DIR/enclaves/NODE/permissions.xml, the DDS permissions each enclave "
        "gets. On a ROS install with DDS-Security: ros2 security generate_artifacts -k DIR/keystore -p "
        "DIR/policy.xml, then run each node with ROS_SECURITY_KEYSTORE=DIR/keystore ROS_SECURITY_ENABLE=true "
        "ROS_SECURITY_STRATEGY=Enforce and --ros-args --enclave /pusher_rl/NODE.",
    )
    p.add_argument("--keystore", required=True, help="directory to write into (made if new)")
    p.add_argument("--namespace", default="/", help="the pipeline's namespace (launch files' namespace:=)")
    p.add_argument("--domain-id", type=int, default=0, help="the DDS domain the permissions allow (ROS_DOMAIN_ID)")
    p.add_argument("--days", type=int, default=365, help="how long the permissions are valid")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not args.namespace.startswith("/"):
        raise UserError(f"--namespace {args.namespace!r}: expected an absolute namespace such as / or /arm2")
    if not 0 <= args.domain_id <= 232:
        raise UserError(f"--domain-id {args.domain_id}: expected 0-232")
    if args.days < 1:
        raise UserError(f"--days {args.days}: expected at least 1")
    out = check_output_dir(args.keystore, "--keystore")
    write_text_atomic(out / "policy.xml", xml_text(policy_xml(args.namespace)))
    for node in NODE_GRAPH:
        path = Path(out, "enclaves", node, "permissions.xml")
        write_text_atomic(path, xml_text(permissions_xml(node, args.namespace, args.domain_id, args.days)))
    print(f"wrote {out / 'policy.xml'} and the permissions of {len(NODE_GRAPH)} enclaves "
          f"({', '.join(enclave_path(n) for n in NODE_GRAPH)}) under {out / 'enclaves'}")
    return 0
