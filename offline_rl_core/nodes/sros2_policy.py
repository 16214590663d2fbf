"""Least-privilege SROS2 permissions for the project's nodes (no ROS needed to write them).

Each node runs in its own enclave (``/pusher_rl/<node>``) and may publish, subscribe, serve
and call exactly what it does in this package, nothing else: the policy node cannot
publish weights, nothing but the learner can, and only the mux and the recorder's
scripted driver command the arm. From :data:`NODE_GRAPH`:

- ``policy.xml``: an SROS2 policy (the format of sros2's ``policy.xsd``) that
  ``ros2 security generate_artifacts -k KEYSTORE -p policy.xml`` turns into a keystore with
  one signed enclave per node, on a ROS install whose DDS has DDS-Security;
- ``enclaves/<node>/permissions.xml``: the DDS permissions document each enclave gets (the
  OMG DDS-Security format sros2 renders from the policy, before the permissions CA signs it
  as ``permissions.p7s``), to read and review, or to sign with your own CA.

Names are ROS names relative to ``namespace``; a DDS topic is the ROS name prefixed ``rt``
(topics), ``rq``/``rr`` with ``Request``/``Reply`` (services), as rmw maps them.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from xml.etree import ElementTree as ET

from ..data.raw_topics.spec import ACTION_LABEL_TOPIC

POLICY_VERSION = "0.2.0"  # sros2's policy format with <enclaves>
ENCLAVE_ROOT = "/pusher_rl"
PERMISSIONS_SCHEMA = "http://www.omg.org/spec/DDS-SECURITY/20170901/omg_shared_ca_permissions.xsd"

# What every rclpy node does: log, announce and serve its parameters, follow sim time.
COMMON_PUBLISH = ("/rosout", "/parameter_events")
COMMON_SUBSCRIBE = ("/clock", "/parameter_events")
PARAMETER_SERVICES = tuple(f"~/{name}" for name in (
    "describe_parameters", "get_parameter_types", "get_parameters", "list_parameters", "set_parameters",
    "set_parameters_atomically", "get_type_description"))

COMMANDS = tuple(f"pusher/command/{source}" for source in ("expert", "random", "policy", "human"))
# The e-stop: heard by every node that acts or trains, pressed and reset only by the operator.
ESTOP, ESTOP_RESET = "estop", "estop/reset"
SIM_OUT = ("/clock", "pusher/state", "joint_states", "pusher/target", "pusher/fingertip", "pusher/transition")


@dataclass(frozen=True)
class NodeAccess:
    publish: tuple[str, ...] = ()
    subscribe: tuple[str, ...] = ()
    reply: tuple[str, ...] = ()  # services it serves
    request: tuple[str, ...] = ()  # services it calls
    status: bool = True  # publishes ~/status
    diagnostics: bool = True  # publishes /diagnostics (offline_rl_core.nodes.diagnostics)


NODE_GRAPH: dict[str, NodeAccess] = {
    "sim": NodeAccess(publish=SIM_OUT + ("markers",),
                      subscribe=("pusher/command",) + COMMANDS + ("effort_controller/commands", ESTOP,
                                                                   "episode_label"),
                      reply=("pusher/reset", ESTOP_RESET)),
    "policy": NodeAccess(publish=("policy/action", "policy/provenance", "effort_controller/commands",
                                  "episode_label"),  # with end_on_success: its classifier's labels
                         subscribe=("pusher/state", "pusher/target", "pusher/fingertip", "learner/weights", ESTOP),
                         reply=(ESTOP_RESET,)),
    "mux": NodeAccess(publish=("pusher/command/policy", "pusher/command/human", "corrections/intervening"),
                      subscribe=("policy/action", "teleop/action", "pusher/state", ESTOP), reply=(ESTOP_RESET,)),
    "corrector": NodeAccess(publish=("teleop/action", "episode_label", ACTION_LABEL_TOPIC),
                            subscribe=("pusher/state", "pusher/target", "pusher/fingertip", "joy"), status=False),
    "learner": NodeAccess(publish=("~/weights",), subscribe=("pusher/transition", ACTION_LABEL_TOPIC, ESTOP),
                          reply=(ESTOP_RESET,)),
    # driving (collect) or passive: every topic of the pipeline, never a weights publisher
    "recorder": NodeAccess(publish=("pusher/command/expert", "pusher/command/random"),
                           subscribe=SIM_OUT[1:] + COMMANDS + (
                               "policy/action", "policy/provenance", "teleop/action", "corrections/intervening",
                               "effort_controller/commands", "learner/weights", "/tf", "/tf_static", ESTOP,
                               "episode_label", ACTION_LABEL_TOPIC),
                           status=False),
    "trainer": NodeAccess(publish=("~/progress",), status=False),
    # the arm's markers from a real arm's joint states (ros2 run viz markers)
    "markers": NodeAccess(publish=("markers",), subscribe=("joint_states", "goal", "pusher/state", "pusher/target"),
                          status=False),
    # a person's tools (ros2 topic/param/service): watch, set parameters, reset episodes
    "operator": NodeAccess(publish=(ESTOP,),
                           subscribe=("sim/status", "policy/status", "mux/status", "learner/status",
                                      "trainer/progress", "policy/provenance", "corrections/intervening",
                                      "/diagnostics", "markers", "episode_label"),
                           request=("pusher/reset", ESTOP_RESET) + tuple(
                               f"{node}/{service[2:]}" for node in
                               ("sim", "policy", "mux", "corrector", "learner", "recorder", "trainer", "markers")
                               for service in PARAMETER_SERVICES),
                           status=False, diagnostics=False),
}


def enclave_path(node: str) -> str:
    return f"{ENCLAVE_ROOT}/{node}"


def fully_qualified(name: str, namespace: str, node: str) -> str:
    """A ROS name as rcl expands it: absolute as is, ``~`` the node's, otherwise in ``namespace``."""
    ns = namespace.rstrip("/") + "/"
    if name.startswith("/"):
        return name
    if name.startswith("~"):
        return f"{ns}{node}{name[1:]}"
    return ns + name


def _access(node: str) -> NodeAccess:
    a = NODE_GRAPH[node]
    publish = a.publish + (("~/status",) if a.status else ()) + (("/diagnostics",) if a.diagnostics else ()) + \
        COMMON_PUBLISH
    return NodeAccess(publish=_unique(publish), subscribe=_unique(a.subscribe + COMMON_SUBSCRIBE),
                      reply=_unique(a.reply + PARAMETER_SERVICES), request=a.request, status=a.status,
                      diagnostics=a.diagnostics)


def _unique(names) -> tuple[str, ...]:
    return tuple(dict.fromkeys(names))


def policy_xml(namespace: str = "/") -> ET.Element:
    """The SROS2 policy of every node (``ros2 security generate_artifacts -p``)."""
    root = ET.Element("policy", version=POLICY_VERSION)
    enclaves = ET.SubElement(root, "enclaves")
    for node in NODE_GRAPH:
        a = _access(node)
        enclave = ET.SubElement(enclaves, "enclave", path=enclave_path(node))
        profiles = ET.SubElement(enclave, "profiles")
        profile = ET.SubElement(profiles, "profile", ns=namespace, node=node)
        for tag, item, attribute, names in (("topics", "topic", "publish", a.publish),
                                            ("topics", "topic", "subscribe", a.subscribe),
                                            ("services", "service", "reply", a.reply),
                                            ("services", "service", "request", a.request)):
            if names:
                group = ET.SubElement(profile, tag, {attribute: "ALLOW"})
                for name in names:
                    ET.SubElement(group, item).text = name
    return root


def permissions_xml(node: str, namespace: str = "/", domain_id: int = 0, days: int = 365,
                    now: dt.datetime | None = None) -> ET.Element:
    """The DDS permissions document of one node's enclave: its allowed DDS topics, all else denied."""
    a = _access(node)
    fq = lambda name: fully_qualified(name, namespace, node)  # noqa: E731
    publish = [f"rt{fq(n)}" for n in a.publish] + [f"rr{fq(n)}Reply" for n in a.reply] + \
        [f"rq{fq(n)}Request" for n in a.request]
    subscribe = [f"rt{fq(n)}" for n in a.subscribe] + [f"rq{fq(n)}Request" for n in a.reply] + \
        [f"rr{fq(n)}Reply" for n in a.request]
    start = (now or dt.datetime.now(dt.timezone.utc)).replace(microsecond=0, tzinfo=None)
    root = ET.Element("dds", {"xmlns:xsi": "http://www.w3.org/2001/XMLSchema-instance",
                              "xsi:noNamespaceSchemaLocation": PERMISSIONS_SCHEMA})
    grant = ET.SubElement(ET.SubElement(root, "permissions"), "grant", name=enclave_path(node))
    ET.SubElement(grant, "subject_name").text = f"CN={enclave_path(node)}"
    validity = ET.SubElement(grant, "validity")
    ET.SubElement(validity, "not_before").text = start.isoformat()
    ET.SubElement(validity, "not_after").text = (start + dt.timedelta(days=days)).isoformat()
    rule = ET.SubElement(grant, "allow_rule")
    ET.SubElement(ET.SubElement(rule, "domains"), "id").text = str(int(domain_id))
    for tag, names in (("publish", publish), ("subscribe", subscribe)):
        if names:
            topics = ET.SubElement(ET.SubElement(rule, tag), "topics")
            for name in sorted(set(names)):
                ET.SubElement(topics, "topic").text = name
    ET.SubElement(grant, "default").text = "DENY"
    return root


def xml_text(root: ET.Element) -> str:
    ET.indent(root, space="  ")
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
