"""What every participant says it has: rmw's ``ros_discovery_info`` topic, read from Python.

Each ROS 2 process (a DDS participant) publishes ``rmw_dds_common/ParticipantEntitiesInfo``
on the DDS topic ``ros_discovery_info``: its nodes, and the gids of every reader and writer
each node owns. The rmw's graph cache joins these with DDS endpoint discovery, which
arrives separately and, on a loaded machine, can lag by seconds: a node's ``/rosout``
writer is known while its ``/clock`` writer is not yet. Comparing the announced gids with
the discovered endpoints tells the shim what it has not seen yet.

rclpy cannot subscribe to that topic itself: rcl makes every name absolute
(``/ros_discovery_info``), and the rmw publishes it without the slash. So the subscription
is made one layer down, on the rmw (``rmw_create_subscription``, ``rmw_take_serialized_message``)
through ctypes, and each message is deserialised with rclpy's own ``deserialize_message``.
The C structs below mirror rmw/types.h and rcutils/allocator.h, stable since Humble.
``DiscoveryInfo.open`` returns None where any of that is unavailable (another rmw, a
changed ABI): the caller then falls back to waiting for a quiet graph.
"""

from __future__ import annotations

import ctypes
import time
from ctypes import (POINTER, Structure, byref, c_bool, c_char_p, c_int, c_int32, c_int64, c_size_t, c_uint8, c_uint64,
                    c_void_p)

TOPIC = b"ros_discovery_info"
RMW_RET_OK = 0


class _Time(Structure):  # rmw_time_t
    _fields_ = [("sec", c_uint64), ("nsec", c_uint64)]


class _Qos(Structure):  # rmw_qos_profile_t
    _fields_ = [("history", c_int), ("depth", c_size_t), ("reliability", c_int), ("durability", c_int),
                ("deadline", _Time), ("lifespan", _Time), ("liveliness", c_int),
                ("liveliness_lease_duration", _Time), ("avoid_ros_namespace_conventions", c_bool)]


class _SubscriptionOptions(Structure):  # rmw_subscription_options_t
    _fields_ = [("rmw_specific_subscription_payload", c_void_p), ("ignore_local_publications", c_bool),
                ("require_unique_network_flow_endpoints", c_int), ("content_filter_options", c_void_p)]


class _Gid(Structure):  # rmw_gid_t
    _fields_ = [("implementation_identifier", c_char_p), ("data", c_uint8 * 16)]


class _MessageInfo(Structure):  # rmw_message_info_t
    _fields_ = [("source_timestamp", c_int64), ("received_timestamp", c_int64),
                ("publication_sequence_number", c_uint64), ("reception_sequence_number", c_uint64),
                ("publisher_gid", _Gid), ("from_intra_process", c_bool)]


class _Allocator(Structure):  # rcutils_allocator_t
    _fields_ = [("allocate", c_void_p), ("deallocate", c_void_p), ("reallocate", c_void_p),
                ("zero_allocate", c_void_p), ("state", c_void_p)]


class _Bytes(Structure):  # rcutils_uint8_array_t, i.e. rmw_serialized_message_t
    _fields_ = [("buffer", POINTER(c_uint8)), ("buffer_length", c_size_t), ("buffer_capacity", c_size_t),
                ("allocator", _Allocator)]


# the rmw publishes it reliable, transient local, one sample per participant: a late
# reader gets every participant's latest
_KEEP_LAST, _RELIABLE, _TRANSIENT_LOCAL = 1, 1, 1


class DiscoveryInfo:
    """The latest ``ParticipantEntitiesInfo`` of each participant, read as it arrives."""

    def __init__(self, node):
        import rclpy
        from rclpy.type_support import check_for_type_support
        from rmw_dds_common.msg import ParticipantEntitiesInfo

        self._msg_type = ParticipantEntitiesInfo
        check_for_type_support(ParticipantEntitiesInfo)
        capsule_pointer = ctypes.pythonapi.PyCapsule_GetPointer
        capsule_pointer.restype, capsule_pointer.argtypes = c_void_p, [ctypes.py_object, c_char_p]
        type_support = capsule_pointer(ParticipantEntitiesInfo._TYPE_SUPPORT, None)

        # already loaded by rclpy: dlopen finds them by soname
        rcl = ctypes.CDLL("librcl.so")
        rcl.rcl_node_get_rmw_handle.restype, rcl.rcl_node_get_rmw_handle.argtypes = c_void_p, [c_void_p]
        rmw = ctypes.CDLL(f"lib{rclpy.get_rmw_implementation_identifier()}.so")
        rmw.rmw_get_default_subscription_options.restype = _SubscriptionOptions
        rmw.rmw_create_subscription.restype = c_void_p
        rmw.rmw_create_subscription.argtypes = [c_void_p, c_void_p, c_char_p, POINTER(_Qos),
                                                POINTER(_SubscriptionOptions)]
        take = rmw.rmw_take_serialized_message_with_info
        take.restype = c_int32
        take.argtypes = [c_void_p, POINTER(_Bytes), POINTER(c_bool), POINTER(_MessageInfo), c_void_p]
        rmw.rmw_destroy_subscription.restype, rmw.rmw_destroy_subscription.argtypes = c_int32, [c_void_p, c_void_p]
        rcutils = ctypes.CDLL("librcutils.so")
        rcutils.rcutils_get_default_allocator.restype = _Allocator
        rcutils.rcutils_uint8_array_init.restype = c_int32
        rcutils.rcutils_uint8_array_init.argtypes = [POINTER(_Bytes), c_size_t, POINTER(_Allocator)]
        rcutils.rcutils_uint8_array_fini.restype, rcutils.rcutils_uint8_array_fini.argtypes = c_int32, [POINTER(_Bytes)]
        self._rmw, self._rcutils = rmw, rcutils

        self._rmw_node = rcl.rcl_node_get_rmw_handle(node.handle.pointer)
        if not self._rmw_node:
            raise OSError("the node has no rmw handle")
        self._buffer = _Bytes()
        allocator = rcutils.rcutils_get_default_allocator()
        if rcutils.rcutils_uint8_array_init(byref(self._buffer), 4096, byref(allocator)) != RMW_RET_OK:
            raise OSError("cannot allocate a message buffer")
        qos = _Qos(history=_KEEP_LAST, depth=1000, reliability=_RELIABLE, durability=_TRANSIENT_LOCAL,
                   avoid_ros_namespace_conventions=True)
        options = rmw.rmw_get_default_subscription_options()
        self._subscription = rmw.rmw_create_subscription(self._rmw_node, type_support, TOPIC, byref(qos),
                                                         byref(options))
        if not self._subscription:
            rcutils.rcutils_uint8_array_fini(byref(self._buffer))
            raise OSError("rmw_create_subscription refused ros_discovery_info")
        self.participants: dict[bytes, object] = {}  # participant gid -> its latest ParticipantEntitiesInfo
        # participant gid -> when it published that one (ns since the epoch, its clock): a
        # participant announces again whenever one of its nodes or endpoints comes or goes
        self.announced_ns: dict[bytes, int] = {}

    @classmethod
    def open(cls, node) -> "DiscoveryInfo | None":
        try:
            return cls(node)
        except (ImportError, OSError, AttributeError, TypeError, ValueError):
            return None

    def poll(self) -> dict[bytes, object]:
        """Take what has arrived; returns ``participants``."""
        from rclpy.serialization import deserialize_message

        taken, info = c_bool(False), _MessageInfo()
        while True:
            rc = self._rmw.rmw_take_serialized_message_with_info(self._subscription, byref(self._buffer),
                                                                 byref(taken), byref(info), None)
            if rc != RMW_RET_OK or not taken.value:
                return self.participants
            raw = ctypes.string_at(self._buffer.buffer, self._buffer.buffer_length)
            msg = deserialize_message(raw, self._msg_type)
            gid = bytes(msg.gid.data)
            self.participants[gid] = msg
            self.announced_ns[gid] = int(info.source_timestamp)

    def close(self) -> None:
        """Destroy the subscription (before its node is destroyed)."""
        if self._subscription:
            self._rmw.rmw_destroy_subscription(self._rmw_node, self._subscription)
            self._subscription = None
            self._rcutils.rcutils_uint8_array_fini(byref(self._buffer))


def discovered_gids(node) -> set[bytes]:
    """Gids of every reader and writer the node's graph knows: topics and services alike
    (services are request/reply topics at the DDS level, announced like any other)."""
    found: set[bytes] = set()
    for name, _ in node.get_topic_names_and_types(no_demangle=True):
        for endpoint in (node.get_publishers_info_by_topic(name, no_mangle=True)
                         + node.get_subscriptions_info_by_topic(name, no_mangle=True)):
            found.add(bytes(endpoint.endpoint_gid))
    return found


def _hidden(name: str) -> bool:
    return name.startswith("_")


def _of_the_graph(node, participants: dict, own_node: str):
    """(gid, {(namespace, name): NodeEntitiesInfo}) of each participant whose nodes are in
    ``node``'s graph now (a participant that left is dropped with its nodes), but this one's."""
    in_graph = {(ns, name) for name, ns in node.get_node_names_and_namespaces()}
    for gid, info in participants.items():
        nodes = {(n.node_namespace, n.node_name): n for n in info.node_entities_info_seq}
        if nodes.keys() & in_graph and not any(name == own_node for _, name in nodes):
            yield gid, nodes


def undiscovered_endpoints(node, announcements: DiscoveryInfo, own_node: str) -> int | None:
    """How many endpoints the participants of the graph's nodes announced that ``node``
    has not discovered yet; None while a node of the graph has no announcement here yet
    (its endpoints are unknown). ``own_node``: this process's node, skipped."""
    announced: set[bytes] = set()
    described: set[tuple[str, str]] = set()
    for _, nodes in _of_the_graph(node, announcements.participants, own_node):
        described |= nodes.keys()
        for n in nodes.values():
            announced |= {bytes(g.data) for g in list(n.reader_gid_seq) + list(n.writer_gid_seq)}
    in_graph = {(ns, name) for name, ns in node.get_node_names_and_namespaces()}
    if any(key not in described and key[1] != own_node for key in in_graph):
        return None
    return len(announced - discovered_gids(node)) if announced else 0


def last_change_age_s(node, announcements: DiscoveryInfo, own_node: str) -> float:
    """Seconds since the graph's participants last announced a change, by their own clocks:
    how long the graph has been as it is, whenever this process joined. A node being built
    announces each endpoint it adds. Participants of hidden nodes only (another ``ros2``
    call) do not count."""
    graph = _of_the_graph(node, announcements.participants, own_node)
    stamps = [announcements.announced_ns[gid] for gid, nodes in graph if not all(_hidden(name) for _, name in nodes)]
    return (time.time_ns() - max(stamps)) / 1e9 if stamps else float("inf")
