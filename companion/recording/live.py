"""The live view: the recorder's topics served over Foxglove's WebSocket protocol.

``--live [HOST:PORT]`` on ``fly`` or ``sim fly`` starts foxglove-sdk's WebSocket server
(:func:`foxglove.start_server`, its own :class:`foxglove.Context`, so nothing else the process
logs reaches it) with one channel per recorder topic, same names and schemas as the file. It
is a sink of the recording writer: each message, once encoded on the writer's thread, is
handed to the server, which queues it per client (``BACKLOG`` messages) and drops the oldest
for a client that does not keep up. So a slow or stalled viewer costs the flight nothing: the
event loop never sees the server, and the writer's hand-off does not wait on a socket.

Open it in Foxglove with "Open connection", ``ws://HOST:PORT``.
"""

from __future__ import annotations

import logging

import foxglove

from companion.recording.topics import TOPICS

log = logging.getLogger(__name__)

#: Messages queued per client before the oldest is dropped: about 2 s of every topic.
BACKLOG = 2048
DEFAULT_PORT = 8765


class LiveViewError(RuntimeError):
    """The live view cannot start (the address is bad or in use)."""


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT``, ``HOST`` or ``:PORT`` (default 127.0.0.1:8765) as (host, port)."""
    host, _, port = text.rpartition(":") if ":" in text else (text, "", "")
    host = host or "127.0.0.1"
    try:
        number = int(port) if port else DEFAULT_PORT
    except ValueError:
        raise LiveViewError(f"live view address {text!r}: the port must be a number") from None
    if not 0 <= number <= 65535:
        raise LiveViewError(f"live view address {text!r}: port {number} out of 0..65535")
    return host, number


class LiveView:
    """The server and its channels; :meth:`sink` is the writer's sink."""

    def __init__(self, host: str, port: int):
        self.context = foxglove.Context()
        try:
            self.server = foxglove.start_server(name="companion", host=host, port=port,
                                                context=self.context,
                                                message_backlog_size=BACKLOG)
        except Exception as error:  # noqa: BLE001 - foxglove raises its own error types
            raise LiveViewError(f"live view on {host}:{port} did not start: {error}") from None
        self.channels = {topic.name: foxglove.Channel(
            topic.name, schema=topic.schema, context=self.context,
            message_encoding="json" if topic.schema.encoding == "jsonschema" else "protobuf")
            for topic in TOPICS}
        log.info("live view on ws://%s:%d", host, self.server.port)

    @property
    def port(self) -> int:
        return self.server.port

    def sink(self, topic: str, t_ns: int, data: bytes) -> None:
        """One encoded message to every connected client (queued; never waits)."""
        self.channels[topic].log(data, log_time=t_ns)

    def close(self) -> None:
        self.server.stop()
