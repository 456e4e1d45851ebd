"""The live view (issue 22): a real WebSocket client, speaking Foxglove's protocol as Foxglove
does, watches a simulated flight served with ``--live`` and receives odometry and depth."""

from __future__ import annotations

import asyncio
import json
import socket
import struct
import threading

import pytest
import websockets
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from companion.config import load_config
from companion.launch import simulated
from companion.recording import live, topics
from ports import free_tcp_port

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

#: Foxglove's WebSocket subprotocol (foxglove-sdk) and its binary MessageData opcode.
SUBPROTOCOL, MESSAGE_DATA = "foxglove.sdk.v1", 0x01
WATCHED = (topics.ODOMETRY.name, topics.DEPTH_METRIC.name)


async def watch(port: int, timeout_s: float = 120.0) -> dict[str, bytes]:
    """Connect (retrying until the flight's server is up), subscribe to :data:`WATCHED` and
    return the first message of each."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while True:
        try:
            client = await websockets.connect(f"ws://127.0.0.1:{port}",
                                              subprotocols=[SUBPROTOCOL])
            break
        except OSError:
            if loop.time() > deadline:
                raise
            await asyncio.sleep(0.1)
    async with client:
        channels, first = {}, {}
        while not set(WATCHED) <= set(channels):
            message = json.loads(await asyncio.wait_for(client.recv(), timeout_s))
            if message["op"] == "advertise":
                channels.update({c["topic"]: c for c in message["channels"]})
        subscriptions = {i: topic for i, topic in enumerate(WATCHED, start=1)}
        await client.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": i, "channelId": channels[topic]["id"]} for i, topic in subscriptions.items()]}))
        while len(first) < len(WATCHED):
            data = await asyncio.wait_for(client.recv(), timeout_s)
            if isinstance(data, bytes) and data[0] == MESSAGE_DATA:
                subscription, _log_time = struct.unpack_from("<IQ", data, 1)
                first.setdefault(subscriptions[subscription], data[13:])
        return first, channels


def test_a_websocket_client_receives_odometry_and_depth_during_a_flight(tmp_path):
    port = free_tcp_port()
    config = load_config(None, [f"recorder.directory={tmp_path}", "flight.mission_timeout_s=5"])
    outcome = {}

    def fly():
        outcome["summary"] = simulated.run(config, simulated.SimMission(world="dome"),
                                           record=True, live=f"127.0.0.1:{port}")

    flight = threading.Thread(target=fly, daemon=True)
    flight.start()
    first, channels = asyncio.run(watch(port))
    flight.join(timeout=300)
    assert "summary" in outcome, "the flight did not end"

    odometry = json.loads(first[topics.ODOMETRY.name])
    assert len(odometry["position"]) == 3 and len(odometry["quaternion_wxyz"]) == 4
    assert channels[topics.DEPTH_METRIC.name]["schemaName"] == "foxglove.RawImage"
    depth = RawImage()
    depth.ParseFromString(first[topics.DEPTH_METRIC.name])
    assert depth.encoding == "16UC1" and depth.width * depth.height * 2 == len(depth.data)
    assert outcome["summary"]["recording"]["error"] is None


@pytest.mark.parametrize("text, expected", [
    ("", ("127.0.0.1", 8765)), ("0.0.0.0", ("0.0.0.0", 8765)), (":9000", ("127.0.0.1", 9000)),
    ("10.0.0.2:9001", ("10.0.0.2", 9001))])
def test_live_addresses(text, expected):
    assert live.parse_address(text) == expected


@pytest.mark.parametrize("text, words", [("host:port", "must be a number"),
                                         ("host:70000", "out of 0..65535")])
def test_a_bad_live_address_is_a_clear_error(text, words):
    with pytest.raises(live.LiveViewError, match=words):
        live.parse_address(text)


def test_a_port_in_use_is_a_clear_error():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        with pytest.raises(live.LiveViewError, match="did not start"):
            live.LiveView("127.0.0.1", taken.getsockname()[1])
