"""``visualization_msgs/MarkerArray`` from ``offline_rl_core.nodes.arm_markers`` records.

The arm's markers replace themselves (same namespace and id every time), so RViz and
Foxglove show one arm that moves; ``lifetime`` is left at 0 (forever) and ``frame_locked``
off: the frame is the world.
"""

from __future__ import annotations

from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker as MarkerMsg
from visualization_msgs.msg import MarkerArray

from offline_rl_core.nodes.arm_markers import FRAME, SPHERE, Marker

MARKERS_TOPIC = "markers"


def marker_array(markers: list[Marker], stamp, frame: str = FRAME) -> MarkerArray:
    out = MarkerArray()
    for m in markers:
        msg = MarkerMsg(ns=m.ns, id=m.id, type=m.type, action=MarkerMsg.ADD)
        msg.header.frame_id = frame
        msg.header.stamp = stamp
        msg.pose.orientation.w = 1.0
        if m.type == SPHERE:
            msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = m.position
        else:
            msg.points = [Point(x=p[0], y=p[1], z=p[2]) for p in m.points]
        msg.scale.x, msg.scale.y, msg.scale.z = m.scale
        msg.color = ColorRGBA(r=m.color[0], g=m.color[1], b=m.color[2], a=m.color[3])
        out.markers.append(msg)
    return out
