"""The recorder's writer (companion/recording/writer.py): what reaches the file, what is
dropped and counted, and what survives a SIGKILL or a failing disk (docs/recording.md)."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import threading
import time

import foxglove
import foxglove.messages as fm
import pytest
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.records import Chunk, Message

from autonomy.options import OptionError
from companion.recording.inspect import summarise
from companion.recording.options import RecorderOptions
from companion.recording.storage import RecordingError
from companion.recording.writer import (AFTER_CLOSE, BAD_MESSAGE, DISK_RESERVE, QUEUE_FULL,
                                        WRITE_FAILED, RecordingWriter)

IMAGE = fm.CompressedImage.get_schema()
LOG = fm.Log.get_schema()
JSON = foxglove.Schema(name="test.Sample", encoding="jsonschema",
                       data=json.dumps({"type": "object"}).encode())
PLENTY = lambda directory: 10**15  # noqa: E731  a disk that never fills


def image(i: int) -> bytes:
    return fm.CompressedImage(format="jpeg", data=bytes([i % 256]) * 1000).encode()


def sample(i: int) -> bytes:
    return json.dumps({"i": i}).encode()


def open_writer(path, *, free_bytes=PLENTY, **options) -> RecordingWriter:
    writer = RecordingWriter(path, RecorderOptions(**options), metadata={"vehicle": "test"},
                             free_bytes=free_bytes)
    writer.add_channel("/camera/image", IMAGE, droppable=True)
    writer.add_channel("/imu", JSON)
    writer.add_channel("/flight/events", LOG)
    return writer


class Gate:
    """An encode() that holds the writer's thread until opened, so a test can fill the
    queues deterministically behind it."""

    def __init__(self):
        self.entered, self.opened = threading.Event(), threading.Event()

    def __call__(self) -> bytes:
        self.entered.set()
        self.opened.wait(10.0)
        return sample(-1)

    def hold(self, writer: RecordingWriter) -> None:
        writer.put("/imu", 0, self)
        assert self.entered.wait(10.0)


def messages(path) -> list[tuple[str, int, bytes]]:
    with open(path, "rb") as file:
        return [(channel.topic, message.log_time, message.data) for _, channel, message in
                make_reader(file).iter_messages(log_time_order=False)]


def test_every_message_is_written_with_its_channel_schema_and_metadata(tmp_path):
    path = tmp_path / "flight.mcap"
    writer = open_writer(path)
    for i in range(50):
        writer.put("/imu", 1000 + i, lambda i=i: sample(i))
    writer.put("/flight/events", 2000, lambda: fm.Log(message="takeoff").encode())
    stats = writer.close()

    assert stats.written == {"/imu": 50, "/flight/events": 1} and stats.dropped == {}
    assert stats.error == "" and stats.bytes_written == path.stat().st_size
    with open(path, "rb") as file:
        reader = make_reader(file)
        summary = reader.get_summary()
        channels = {c.topic: (c.message_encoding, summary.schemas[c.schema_id].name)
                    for c in summary.channels.values()}
        metadata = {record.name: record.metadata for record in reader.iter_metadata()}
    assert channels == {"/camera/image": ("protobuf", "foxglove.CompressedImage"),
                        "/imu": ("json", "test.Sample"),
                        "/flight/events": ("protobuf", "foxglove.Log")}
    assert messages(path)[:2] == [("/imu", 1000, sample(0)), ("/imu", 1001, sample(1))]
    assert metadata["companion"] == {"vehicle": "test"}
    assert json.loads(metadata["recording_stats"]["written"]) == stats.written
    assert json.loads(metadata["recording_stats"]["dropped"]) == {}


def test_messages_keep_arrival_order_and_read_back_in_time_order(tmp_path):
    path = tmp_path / "flight.mcap"
    writer = open_writer(path)
    for t in (30, 10, 20):
        writer.put("/imu", t, lambda t=t: sample(t))
    writer.close()
    assert [t for _, t, _ in messages(path)] == [30, 10, 20]
    with open(path, "rb") as file:
        assert [m.log_time for _, _, m in make_reader(file).iter_messages()] == [10, 20, 30]


def test_encoding_runs_on_the_writers_thread_not_the_callers(tmp_path):
    threads = []
    writer = open_writer(tmp_path / "flight.mcap")
    writer.put("/imu", 1, lambda: threads.append(threading.current_thread()) or sample(1))
    writer.close()
    assert threads and threads[0] is not threading.current_thread()


def test_a_full_image_queue_drops_the_newest_image_and_counts_it(tmp_path):
    gate = Gate()
    writer = open_writer(tmp_path / "flight.mcap", camera_queue=4)
    gate.hold(writer)
    for i in range(7):
        writer.put("/camera/image", 10 + i, lambda i=i: image(i))
    writer.put("/imu", 20, lambda: sample(20))
    gate.opened.set()
    stats = writer.close()
    assert stats.dropped == {"/camera/image": {QUEUE_FULL: 3}}
    assert stats.written == {"/camera/image": 4, "/imu": 2}
    written_images = [data for topic, _, data in messages(writer.path) if topic == "/camera/image"]
    assert written_images == [image(i) for i in range(4)]  # the oldest kept, the newest dropped


def test_a_full_event_queue_drops_and_counts_but_never_blocks(tmp_path):
    gate = Gate()
    writer = open_writer(tmp_path / "flight.mcap", event_queue=100)
    gate.hold(writer)
    for i in range(105):
        writer.put("/imu", i, lambda i=i: sample(i))
    gate.opened.set()
    stats = writer.close()
    assert stats.dropped == {"/imu": {QUEUE_FULL: 5}}
    assert stats.written == {"/imu": 101}


def test_below_the_disk_reserve_images_are_dropped_and_events_kept(tmp_path):
    seen = []
    writer = open_writer(tmp_path / "flight.mcap", free_bytes=lambda directory: 0)
    writer.add_sink(lambda topic, t, data: seen.append(topic))
    writer.put("/camera/image", 1, lambda: image(1))
    writer.put("/flight/events", 2, lambda: fm.Log(message="land").encode())
    stats = writer.close()
    assert stats.dropped == {"/camera/image": {DISK_RESERVE: 1}}
    assert stats.written == {"/flight/events": 1}
    assert sorted(seen) == ["/camera/image", "/flight/events"]  # the live view still sees it


def test_sinks_get_every_encoded_message_and_a_failing_sink_is_removed(tmp_path, caplog):
    good, calls = [], []

    def failing(topic, t, data):
        calls.append(t)
        raise RuntimeError("viewer gone")

    writer = open_writer(tmp_path / "flight.mcap")
    writer.add_sink(failing)
    writer.add_sink(lambda topic, t, data: good.append((topic, t, data)))
    for i in range(3):
        writer.put("/imu", i, lambda i=i: sample(i))
    stats = writer.close()
    assert good == [("/imu", i, sample(i)) for i in range(3)]
    assert calls == [0]
    assert "removed the sink" in caplog.text and "viewer gone" in caplog.text
    assert stats.written == {"/imu": 3}


def test_bad_messages_are_counted_and_the_recording_goes_on(tmp_path):
    writer = open_writer(tmp_path / "flight.mcap")
    writer.put("/nowhere", 1, lambda: sample(1))
    writer.put("/imu", -5, lambda: sample(2))
    writer.put("/imu", 3, lambda: 1 / 0)
    writer.put("/imu", 4, lambda: "not bytes")
    writer.put("/imu", 5, lambda: sample(5))
    stats = writer.close()
    assert stats.dropped == {"/nowhere": {BAD_MESSAGE: 1}, "/imu": {BAD_MESSAGE: 3}}
    assert stats.written == {"/imu": 1} and stats.error == ""


def test_close_is_idempotent_and_a_put_after_it_is_counted(tmp_path):
    writer = open_writer(tmp_path / "flight.mcap")
    writer.put("/imu", 1, lambda: sample(1))
    first = writer.close()
    writer.put("/imu", 2, lambda: sample(2))
    second = writer.close()
    assert first.written == second.written == {"/imu": 1}
    assert second.dropped == {"/imu": {AFTER_CLOSE: 1}}


def test_an_event_reaches_the_disk_without_waiting_for_a_full_chunk(tmp_path):
    path = tmp_path / "flight.mcap"
    writer = open_writer(path)
    writer.put("/flight/events", 1, lambda: fm.Log(message="arming").encode())
    deadline = time.monotonic() + 10.0
    while writer.stats.written != {"/flight/events": 1} and time.monotonic() < deadline:
        time.sleep(0.05)
    on_disk = summarise(path)  # the file as a power cut now would leave it
    writer.close()
    assert on_disk["complete"] is False
    assert [event["text"] for event in on_disk["events"]] == ["arming"]


def test_a_file_that_cannot_be_opened_is_a_clear_error(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(RecordingError, match="cannot write the recording .*file/flight.mcap"):
        RecordingWriter(tmp_path / "file" / "flight.mcap", RecorderOptions())


def test_bad_channels_and_metadata_are_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="metadata values must be strings; 'speed' is int"):
        RecordingWriter(tmp_path / "a.mcap", RecorderOptions(), metadata={"speed": 3})
    writer = open_writer(tmp_path / "b.mcap")
    with pytest.raises(ValueError, match="has a channel /imu already"):
        writer.add_channel("/imu", JSON)
    with pytest.raises(ValueError, match="cannot record schema encoding 'ros1msg'"):
        writer.add_channel("/ros", foxglove.Schema(name="x", encoding="ros1msg", data=b""))
    writer.close()


@pytest.mark.parametrize("key, value", [("jpeg_quality", 40), ("camera_queue", 0),
                                        ("chunk_kb", 1), ("quota_mb", 0.0),
                                        ("directory", " ")])
def test_recorder_options_reject_bad_values(key, value):
    with pytest.raises(OptionError, match=key):
        RecorderOptions(**{key: value})


# A child process records numbered messages; the parent kills it, or it hits a file size limit.
CHILD = """
import json, os, resource, signal, sys, time
import foxglove
from companion.recording.options import RecorderOptions
from companion.recording.writer import RecordingWriter

path, mode, limit = sys.argv[1], sys.argv[2], int(sys.argv[3])
schema = foxglove.Schema(name="test.Blob", encoding="jsonschema", data=b"{}")
writer = RecordingWriter(path, RecorderOptions(chunk_kb=16))
writer.add_channel("/data", schema)
blob = lambda i: (b"%08d" % i) + os.urandom(2000)  # incompressible: a chunk is about 16 kB
if mode == "limit":
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    for i in range(400):
        writer.put("/data", i, lambda i=i: blob(i))
    stats = writer.close()
    print(json.dumps({"written": stats.written, "dropped": stats.dropped, "error": stats.error}))
else:
    i = 0
    while True:
        writer.put("/data", i, lambda i=i: blob(i))
        i += 1
        written = writer.stats.written.get("/data", 0)
        if written >= limit:
            print("written", written, flush=True)
            limit = 1 << 62
        time.sleep(0.0005)
"""


def run_child(path, mode: str, limit: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", CHILD, str(path), mode, str(limit)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def readable_numbers(path) -> list[int]:
    """The numbered messages a stream reader gets from the start of ``path``, whole chunks
    only, read with mcap's own primitives."""
    numbers = []
    with open(path, "rb") as file:
        try:
            for record in StreamReader(file, emit_chunks=True, validate_crcs=True).records:
                if isinstance(record, Chunk):
                    numbers += [int(m.data[:8]) for m in breakup_chunk(record, validate_crc=True)
                                if isinstance(m, Message)]
        except Exception:  # the cut: everything before it was read
            pass
    return numbers


def test_a_killed_recording_is_readable_up_to_its_last_complete_chunk(tmp_path):
    path = tmp_path / "killed.mcap"
    child = run_child(path, "kill", 100)
    try:
        ready, _, _ = select.select([child.stdout], [], [], 60.0)
        line = child.stdout.readline() if ready else ""
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.wait(10)
    assert line.startswith("written"), child.stderr.read()
    numbers = readable_numbers(path)
    assert len(numbers) >= int(line.split()[1])  # all it had reported written is there
    assert numbers == list(range(len(numbers)))  # and nothing before the cut is missing
    summary = summarise(path)
    assert summary["complete"] is False and summary["messages"] == len(numbers)


def test_a_failing_disk_stops_the_file_not_the_process(tmp_path):
    path, limit = tmp_path / "full.mcap", 200_000
    child = run_child(path, "limit", limit)
    out, err = child.communicate(timeout=120)
    assert child.returncode == 0, err
    stats = json.loads(out)
    assert "File too large" in stats["error"]
    written, failed = stats["written"]["/data"], stats["dropped"]["/data"][WRITE_FAILED]
    assert written > 0 and written + failed == 400
    assert "recording" in err and "stopped: File too large" in err  # logged, once
    assert err.count("stopped:") == 1
    assert path.stat().st_size <= limit
    assert readable_numbers(path) == list(range(written))  # exactly what it counted written
