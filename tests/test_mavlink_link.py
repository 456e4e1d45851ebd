"""MAVLink links from URLs: parsing, real UDP sockets and a real pseudo-terminal, signing."""

import os
import socket
import time

import pytest

from drivers.mavlink.link import LinkAddress, open_link, parse_url
from drivers.mavlink import px4_protocol


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("url, expected", [
    ("udpin://127.0.0.1:14540", LinkAddress("udpin", host="127.0.0.1", port=14540)),
    ("udpout://localhost:14550", LinkAddress("udpout", host="localhost", port=14550)),
    ("tcp://10.0.0.2:5760", LinkAddress("tcp", host="10.0.0.2", port=5760)),
    ("tcpin://0.0.0.0:5760", LinkAddress("tcpin", host="0.0.0.0", port=5760)),
    ("serial:///dev/ttyTHS1:921600", LinkAddress("serial", device="/dev/ttyTHS1", baud=921600)),
    ("serial:///dev/ttyACM0", LinkAddress("serial", device="/dev/ttyACM0", baud=57600)),
    ("pty", LinkAddress("pty")),
])
def test_parse_url_understands_the_connection_strings_people_type(url, expected):
    assert parse_url(url) == expected


@pytest.mark.parametrize("url, complaint", [
    ("", "non-empty"),
    ("127.0.0.1:14540", "no scheme"),
    ("udp://127.0.0.1:14540", "unknown scheme"),
    ("udpin://127.0.0.1", "host:port"),
    ("udpin://:14540", "host:port"),
    ("udpin://127.0.0.1:99999", "port"),
    ("udpin://127.0.0.1:abc", "port"),
    ("udpout://127.0.0.1:14540/extra", "nothing after"),
    ("serial://ttyUSB0:57600", "absolute path"),
    ("serial:///dev/ttyUSB0:fast", "baud"),
    ("serial:///dev/ttyUSB0:0", "baud"),
])
def test_parse_url_rejects_malformed_urls_with_a_clear_message(url, complaint):
    with pytest.raises(ValueError, match=complaint):
        parse_url(url)


def test_udp_links_carry_mavlink2_messages_both_ways():
    port = free_udp_port()
    with open_link(f"udpin://127.0.0.1:{port}") as server, \
            open_link(f"udpout://127.0.0.1:{port}", source_system=255) as client:
        for i in range(5):
            client.mav.heartbeat_send(6, 8, 0, i, 0)
        received = server.receive_pending()
        assert [m.custom_mode for m in received] == [0, 1, 2, 3, 4]
        assert all(m.get_srcSystem() == 255 for m in received)
        server.mav.heartbeat_send(2, 12, 0, 0, 0)  # answers whoever sent to it
        (reply,) = client.receive_pending()
        assert reply.get_type() == "HEARTBEAT" and reply.autopilot == 12
        assert reply.get_msgbuf()[0] == 0xFD  # MAVLink 2 framing


def test_pty_link_is_a_raw_serial_port_a_client_can_open():
    with open_link("pty") as server:
        assert server.pty_path and os.path.exists(server.pty_path)
        with open_link(f"serial://{server.pty_path}:115200", source_system=255) as client:
            client.mav.heartbeat_send(6, 8, 0, 7, 0)
            server.mav.heartbeat_send(2, 12, 0, 9, 0)
            assert [m.custom_mode for m in _wait(server)] == [7]
            assert [m.custom_mode for m in _wait(client)] == [9]


def _wait(link, attempts=200):
    """Messages from a link, polling for up to a second (a pty has no datagram boundaries)."""
    for _ in range(attempts):
        messages = link.receive_pending()
        if messages:
            return messages
        time.sleep(0.005)
    return []


def test_garbage_is_counted_not_returned():
    port = free_udp_port()
    with open_link(f"udpin://127.0.0.1:{port}") as server, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw, \
            open_link(f"udpout://127.0.0.1:{port}") as client:
        raw.sendto(bytes([0xFD, 9, 0, 0, 1, 1, 1, 0, 0, 0]) + b"\xff" * 20, ("127.0.0.1", port))
        client.mav.heartbeat_send(6, 8, 0, 3, 0)
        messages = server.receive_pending()
        assert [m.get_type() for m in messages] == ["HEARTBEAT"]
        assert server.bad_data_count >= 1


def test_signing_rejects_unsigned_messages_except_the_allowlist():
    port = free_udp_port()
    key = bytes(range(32))
    with open_link(f"udpin://127.0.0.1:{port}") as server, \
            open_link(f"udpout://127.0.0.1:{port}", source_system=255) as client:
        server.setup_signing(key, accept_unsigned=px4_protocol.accept_unsigned)
        client.mav.heartbeat_send(6, 8, 0, 0, 0)
        client.mav.radio_status_send(200, 190, 100, 10, 5, 0, 0)
        assert [m.get_type() for m in server.receive_pending()] == ["RADIO_STATUS"]
        client.setup_signing(key)
        client.mav.heartbeat_send(6, 8, 0, 0, 0)
        (heartbeat,) = server.receive_pending()
        assert heartbeat.get_type() == "HEARTBEAT" and heartbeat.get_signed()


def test_signing_key_must_be_32_bytes():
    with open_link("pty") as link:
        with pytest.raises(ValueError, match="32 bytes"):
            link.setup_signing(b"short")
