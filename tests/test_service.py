"""sd_notify as systemd sees it: the exact datagrams on a real AF_UNIX socket, and the watchdog
interval from the environment systemd sets."""

import os
import socket
import uuid

import pytest

from companion.launch.systemd import SystemdNotifier, watchdog_interval_s


@pytest.fixture
def listener(tmp_path):
    """A datagram socket bound at a path, as systemd's notify socket is; yields (env, receive)."""
    path = tmp_path / "notify"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(2.0)
    yield {"NOTIFY_SOCKET": str(path)}, lambda: sock.recv(4096)
    sock.close()


def test_each_verb_sends_the_sd_notify_bytes(listener):
    env, receive = listener
    notifier = SystemdNotifier(env)
    assert notifier.enabled
    assert notifier.ready("flying to goal")
    assert receive() == b"READY=1\nSTATUS=flying to goal"
    assert notifier.status("VINS initialising")
    assert receive() == b"STATUS=VINS initialising"
    assert notifier.watchdog()
    assert receive() == b"WATCHDOG=1"
    assert notifier.extend_timeout(90)
    assert receive() == b"EXTEND_TIMEOUT_USEC=90000000"
    assert notifier.stopping()
    assert receive() == b"STOPPING=1"
    notifier.close()


def test_status_is_one_line_so_it_cannot_inject_assignments(listener):
    env, receive = listener
    notifier = SystemdNotifier(env)
    notifier.status("camera lost\nREADY=1")
    assert receive() == b"STATUS=camera lost READY=1"
    with pytest.raises(ValueError, match="one KEY=VALUE line"):
        notifier.notify("WATCHDOG=1\nREADY=1")
    with pytest.raises(ValueError, match="positive"):
        notifier.extend_timeout(0)


def test_abstract_namespace_socket():
    name = f"companion-test-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2.0)
    try:
        notifier = SystemdNotifier({"NOTIFY_SOCKET": "@" + name})
        assert notifier.watchdog()
        assert sock.recv(4096) == b"WATCHDOG=1"
    finally:
        sock.close()


def test_without_notify_socket_every_call_is_a_no_op():
    notifier = SystemdNotifier({})
    assert not notifier.enabled
    assert not notifier.ready("x") and not notifier.watchdog() and not notifier.stopping()


def test_a_vanished_socket_is_reported_not_raised(tmp_path, caplog):
    notifier = SystemdNotifier({"NOTIFY_SOCKET": str(tmp_path / "nobody-listens")})
    assert notifier.watchdog() is False
    assert notifier.watchdog() is False
    assert len([r for r in caplog.records if "notification" in r.getMessage()]) == 1


def test_watchdog_interval_is_half_the_timeout():
    assert watchdog_interval_s({"WATCHDOG_USEC": "2000000"}) == 1.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "2000000",
                                "WATCHDOG_PID": str(os.getpid())}) == 1.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "500000", "WATCHDOG_PID": "42"}, pid=42) == 0.25


def test_watchdog_off_when_unset_or_meant_for_another_process():
    assert watchdog_interval_s({}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"}, pid=2) is None


@pytest.mark.parametrize("env", [{"WATCHDOG_USEC": "2s"}, {"WATCHDOG_USEC": "0"},
                                 {"WATCHDOG_USEC": "1000", "WATCHDOG_PID": "me"}])
def test_watchdog_garbage_is_a_clear_error(env):
    with pytest.raises(ValueError, match="WATCHDOG_"):
        watchdog_interval_s(env, pid=1)


def test_start_up_asks_systemd_for_more_time_while_the_network_opens(listener):
    """A first TensorRT engine build outlasts TimeoutStartSec: while the open runs, the
    application keeps asking for more time, each request covering three of its steps."""
    import asyncio
    import time

    from companion.launch.real import extending_start_timeout

    env, receive = listener
    result = asyncio.run(extending_start_timeout(
        SystemdNotifier(env), lambda: time.sleep(0.35) or "engine", step_s=0.1))
    assert result == "engine"
    requests = []
    try:
        while True:
            requests.append(receive())
    except TimeoutError:
        pass
    assert len(requests) >= 3
    assert set(requests) == {b"EXTEND_TIMEOUT_USEC=300000"}


def test_a_failing_open_is_raised_not_swallowed():
    import asyncio

    from companion.launch.real import extending_start_timeout

    def broken():
        raise RuntimeError("engine build failed")

    with pytest.raises(RuntimeError, match="engine build failed"):
        asyncio.run(extending_start_timeout(SystemdNotifier({}), broken, step_s=0.05))
