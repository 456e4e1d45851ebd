"""MAVLink links from URLs: parsing, real UDP and TCP sockets, a real pseudo-terminal opened
as a serial port, signing."""

import errno
import logging
import os
import re
import socket
import time

import pytest
import serial

from drivers.mavlink.link import LinkAddress, LinkError, Traffic, open_link, parse_url
from drivers.mavlink import px4_protocol


def free_port(kind=socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_udp_port() -> int:
    return free_port()


@pytest.mark.parametrize("url, expected", [
    ("udpin://127.0.0.1:14540", LinkAddress("udpin", host="127.0.0.1", port=14540)),
    ("udpout://localhost:14550", LinkAddress("udpout", host="localhost", port=14550)),
    ("tcpin://0.0.0.0:5760", LinkAddress("tcpin", host="0.0.0.0", port=5760)),
    ("tcpin://:5760", LinkAddress("tcpin", host="0.0.0.0", port=5760)),
    ("tcpout://10.0.0.2:5760", LinkAddress("tcpout", host="10.0.0.2", port=5760)),
    # tcp:// is deprecated in MAVSDK (cli_arg.cpp): no host or 0.0.0.0 listens, else connects
    ("tcp://10.0.0.2:5760", LinkAddress("tcpout", host="10.0.0.2", port=5760)),
    ("tcp://0.0.0.0:5760", LinkAddress("tcpin", host="0.0.0.0", port=5760)),
    ("tcp://:5760", LinkAddress("tcpin", host="0.0.0.0", port=5760)),
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
    ("serial:///dev/ttyUSB0:92160", "92160 baud is not a rate PX4 can set"),
    ("udpout://0.0.0.0:14540", "0.0.0.0 can be listened on, not sent to: udpin://"),
    ("tcpout://0.0.0.0:5760", "0.0.0.0 can be listened on, not sent to: tcpin://"),
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


def test_a_missing_serial_port_is_named_with_where_to_look():
    with pytest.raises(LinkError) as caught:
        open_link("serial:///dev/ttyTHS9:921600")
    assert str(caught.value) == (
        "serial port /dev/ttyTHS9 at 921600 baud: no such port; list them with "
        "`ls /dev/ttyTHS* /dev/ttyACM* /dev/ttyUSB*` or `companion devices`")


def test_a_serial_port_another_process_holds_is_refused_as_busy():
    with open_link("pty") as px4, open_link(f"serial://{px4.pty_path}:921600"):
        with pytest.raises(LinkError, match=f"serial port {px4.pty_path} at 921600 baud: busy: "
                                            r"another process holds it .*`fuser -v "
                                            f"{px4.pty_path}` names it"):
            open_link(f"serial://{px4.pty_path}:921600")


@pytest.mark.parametrize("failure, words", [
    (serial.SerialException(errno.EACCES, "could not open port: [Errno 13] Permission denied"),
     "permission denied: add the user to the dialout group"),
    (serial.SerialException(errno.ENXIO, "could not open port: [Errno 6] No such device"),
     "no device behind the node (unplugged?)"),
    (ValueError("Failed to set custom baud rate (3000000): [Errno 22] Invalid argument"),
     "the port does not take this baud rate"),
])
def test_a_serial_port_that_will_not_open_says_why_and_what_to_do(monkeypatch, failure, words):
    def refuse(port):
        raise failure
    monkeypatch.setattr(serial.Serial, "open", refuse)
    with pytest.raises(LinkError, match="^" + re.escape(f"serial port /dev/ttyUSB0 at 3000000 "
                                                      f"baud: {words}")):
        open_link("serial:///dev/ttyUSB0:3000000")


def test_a_baud_rate_px4_cannot_set_is_refused_before_opening():
    with pytest.raises(ValueError, match="921601 baud is not a rate PX4 can set its port to"):
        open_link("serial:///dev/ttyTHS1:921601")


def test_a_serial_port_whose_other_end_goes_away_is_lost_not_an_exception():
    with open_link("pty") as px4:
        link = open_link(f"serial://{px4.pty_path}:921600")
    px4.mav.heartbeat_send(2, 12, 0, 0, 0)  # closed: nothing written
    assert link.receive_pending() == []
    assert str(link.lost) == (f"serial port {px4.pty_path} at 921600 baud lost: end of file "
                              "(its other side closed)")
    link.mav.heartbeat_send(6, 8, 0, 0, 0)  # sends nothing while lost, raises nothing
    assert link.receive_pending() == []
    with pytest.raises(LinkError, match="no such port"):
        link.reopen()


def test_tcpin_listens_and_tcpout_connects_both_ways_and_a_client_may_come_again(caplog):
    port = free_port(socket.SOCK_STREAM)
    with open_link(f"tcpin://127.0.0.1:{port}") as server:
        with open_link(f"tcpout://127.0.0.1:{port}", source_system=255) as client:
            client.mav.heartbeat_send(6, 8, 0, 7, 0)
            assert [(m.get_srcSystem(), m.custom_mode) for m in _wait(server)] == [(255, 7)]
            server.mav.heartbeat_send(2, 12, 0, 9, 0)
            assert [m.custom_mode for m in _wait(client)] == [9]
        assert _wait(server, attempts=20) == []  # the client hung up: listening again
        with caplog.at_level(logging.WARNING, logger="drivers.mavlink.link"):
            again = open_link(f"tcp://127.0.0.1:{port}", source_system=254)
        again.mav.heartbeat_send(6, 8, 0, 8, 0)
        assert [(m.get_srcSystem(), m.custom_mode) for m in _wait(server)] == [(254, 8)]
    with again:  # the server is gone: a lost link, reconnected when it listens again
        assert _wait(again, attempts=20) == [] and "lost: end of file" in str(again.lost)
        with open_link(f"tcpin://127.0.0.1:{port}") as server:
            again.reopen()
            again.mav.heartbeat_send(6, 8, 0, 9, 0)
            assert [m.custom_mode for m in _wait(server)] == [9]
    assert "tcp:// is deprecated (as in MAVSDK); it means tcpout://127.0.0.1:" in caplog.text


def test_tcpout_to_nobody_and_tcpin_on_a_taken_port_say_so():
    port = free_port(socket.SOCK_STREAM)
    with pytest.raises(LinkError, match=f"tcpout://127.0.0.1:{port}: cannot connect "
                                        r"\(Connection refused\): check that a MAVLink TCP "
                                        "server listens there"):
        open_link(f"tcpout://127.0.0.1:{port}")
    with open_link(f"tcpin://127.0.0.1:{port}"):
        with pytest.raises(LinkError, match=f"tcpin://127.0.0.1:{port}: cannot listen"):
            open_link(f"tcpin://127.0.0.1:{port}")


@pytest.mark.parametrize("scheme, words", [
    ("udpout", "no bytes at all: check that PX4 or `companion sim serve` listens on "
               "127.0.0.1:{port}"),
    ("udpin", "no bytes at all: check that PX4 sends to this computer's port {port}"),
    ("tcpin", "no bytes at all: check that PX4 or mavlink-router connects to port {port}"),
])
def test_the_silence_of_a_network_link_is_told_in_its_own_terms(scheme, words):
    port = free_port(socket.SOCK_STREAM if scheme == "tcpin" else socket.SOCK_DGRAM)
    with open_link(f"{scheme}://127.0.0.1:{port}") as link:
        assert link.describe_silence(2.0, Traffic()).startswith(
            f"no MAVLink from {scheme}://127.0.0.1:{port} in 2.0 s: {words.format(port=port)}")
        assert link.describe_silence(2.0, Traffic(bytes=10)).endswith(
            "10 bytes arrived but none parse as MAVLink: something that is not MAVLink sends "
            "to it")


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


def test_signing_refuses_unsigned_and_wrongly_signed_messages_and_counts_them_by_sender():
    port = free_udp_port()
    key = bytes(range(32))
    with open_link(f"udpin://127.0.0.1:{port}") as server, \
            open_link(f"udpout://127.0.0.1:{port}", source_system=255,
                      source_component=190) as client:
        server.setup_signing(key, accept_unsigned=px4_protocol.accept_unsigned)
        client.mav.timesync_send(0, 1)
        client.mav.heartbeat_send(6, 8, 0, 0, 0)  # on PX4's allowlist, as RADIO_STATUS
        client.mav.radio_status_send(200, 190, 100, 10, 5, 0, 0)
        assert [m.get_type() for m in server.receive_pending()] == ["HEARTBEAT", "RADIO_STATUS"]
        assert server.refused.summary() == {"unsigned": 1, "bad_signature": 0}
        client.setup_signing(bytes(32 * [7]))  # another key
        client.mav.timesync_send(0, 2)
        assert server.receive_pending() == []
        assert server.refused.summary() == {"unsigned": 1, "bad_signature": 1}
        assert server.refused.last.describe() == \
            "a badly signed TIMESYNC from system 255 component 190"
        assert server.refused.total(sender=(255, 190)) == 2 == server.bad_data_count
        client.setup_signing(key)
        client.mav.timesync_send(0, 3)
        (timesync,) = server.receive_pending()
        assert timesync.get_signed() and timesync.ts1 == 3
        assert server.refused.total() == 2


def test_a_link_that_stops_signing_accepts_unsigned_messages_again():
    port = free_udp_port()
    with open_link(f"udpin://127.0.0.1:{port}") as server, \
            open_link(f"udpout://127.0.0.1:{port}") as client:
        server.setup_signing(bytes(range(32)))
        server.stop_signing()
        client.mav.timesync_send(0, 1)
        assert [m.get_type() for m in server.receive_pending()] == ["TIMESYNC"]
        assert not server.signing_enabled


def test_signing_key_must_be_32_bytes():
    with open_link("pty") as link:
        with pytest.raises(ValueError, match="32 bytes"):
            link.setup_signing(b"short")
