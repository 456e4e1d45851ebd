"""The channels between the flight process's stages: the newest value for readers, every
value for taps, and a faulty tap never reaching the stage that publishes."""

from __future__ import annotations

import logging

from companion.flight.channels import Latest
from companion.flight.context import Channels


def test_readers_get_the_newest_value_and_taps_every_one_in_order():
    channel: Latest[int] = Latest("numbers")
    assert channel.value is None and channel.published == 0
    seen = []
    unsubscribe = channel.subscribe(seen.append)
    for k in range(3):
        channel.publish(k)
    assert channel.value == 2 and seen == [0, 1, 2] and channel.published == 3
    unsubscribe()
    unsubscribe()  # twice is harmless
    channel.publish(3)
    assert seen == [0, 1, 2] and channel.value == 3


def test_a_failing_tap_is_logged_and_dropped_and_the_others_go_on(caplog):
    channel: Latest[str] = Latest("plan")
    seen = []

    def broken(_):
        unsubscribe_broken()  # the tap gives up, then fails
        raise RuntimeError("disk full")
    unsubscribe_broken = channel.subscribe(broken)
    channel.subscribe(seen.append)
    with caplog.at_level(logging.ERROR):
        channel.publish("a")
        channel.publish("b")
    assert channel.value == "b" and seen == ["a", "b"]
    assert sum("tap on channel 'plan' failed" in r.message for r in caplog.records) == 1


def test_every_channel_is_named_after_its_attribute():
    channels = Channels()
    assert {name: channel.name for name, channel in vars(channels).items()} == {
        name: name for name in vars(channels)}
