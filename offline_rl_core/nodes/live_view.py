"""The live view without ROS tooling: Foxglove's WebSocket server streaming ROS topics as they are (no ROS).

Foxglove (the app or the browser page) connects to ``ws://HOST:PORT`` and sees one channel
per topic, each message the topic's own CDR bytes with its ``ros2msg`` schema (the message
definition rosbag2 writes into MCAP files, from rosbags' type store): the 3D panel draws
``markers`` as it would from a bag, the plots read the state and transitions, the
diagnostics panels ``/diagnostics``. Nothing is converted, so the view is the topics.

``foxglove-sdk`` is the optional ``viz`` extra; :func:`available` says whether it is here.
The server listens on loopback unless told otherwise: it has no authentication.
"""

from __future__ import annotations

from ..common.errors import UserError
from ..data.bag.metadata import typestore

LOOPBACK = "127.0.0.1"
DEFAULT_PORT = 8765  # Foxglove's default for a WebSocket connection


def available() -> bool:
    try:
        import foxglove  # noqa: F401
    except ImportError:
        return False
    return True


def ros2msg_schema(msgtype: str) -> bytes:
    """The message definition of ``pkg/msg/Name`` with its dependencies, as MCAP's ros2msg schemas hold it."""
    return typestore().generate_msgdef(msgtype, ros_version=2)[0].encode()


class LiveView:
    """A Foxglove WebSocket server on ``host:port`` (port 0: a free one, see ``port``)."""

    def __init__(self, host: str = LOOPBACK, port: int = DEFAULT_PORT, name: str = "pusher-rl"):
        try:
            import foxglove
        except ImportError:
            raise UserError("the live view needs foxglove-sdk: pip install 'torch==2.13.0' -e '.[viz]'") from None
        self._foxglove = foxglove
        try:
            self.server = foxglove.start_server(name=name, host=host, port=int(port))
        except Exception as exc:  # noqa: BLE001 - the SDK's error for a port in use or a bad host
            raise UserError(f"live view: cannot listen on {host}:{port}: {exc}") from None
        self.host = host
        self.channels: dict[str, object] = {}

    @property
    def port(self) -> int:
        return int(self.server.port)

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def add_topic(self, topic: str, msgtype: str) -> None:
        """A channel for one ROS topic of type ``pkg/msg/Name`` (KeyError: a type rosbags does not know)."""
        if topic in self.channels:
            return
        schema = self._foxglove.Schema(name=msgtype, encoding="ros2msg", data=ros2msg_schema(msgtype))
        self.channels[topic] = self._foxglove.Channel(topic, message_encoding="cdr", schema=schema)

    def log(self, topic: str, raw: bytes, log_time_ns: int) -> None:
        """One message of a topic added with ``add_topic``, its CDR bytes as received."""
        self.channels[topic].log(bytes(raw), log_time=int(log_time_ns))

    def close(self) -> None:
        for channel in self.channels.values():
            channel.close()
        self.server.stop()
