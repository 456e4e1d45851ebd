"""`companion log info` and `companion log recover`: what a field engineer learns from a
recording, complete or cut short, and a cut one made whole (docs/recording.md)."""

from __future__ import annotations

import json
import os
import threading

import foxglove
import foxglove.messages as fm
import pytest
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk

from companion.cli import main
from companion.recording.options import RecorderOptions
from companion.recording.writer import RecordingWriter

START_NS = 5_000_000_000
STEP_NS = 10_000_000  # messages 10 ms apart: 5.99 s
IMU = foxglove.Schema(name="companion.ImuSample", encoding="jsonschema", data=b"{}")


def log(level, text: str) -> bytes:
    return fm.Log(level=level, message=text, name="mission").encode()


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A closed flight: 200 images and 398 IMU samples, a take-off and a failsafe, and 2 images
    dropped because the writer was held up behind its first message while everything was put
    (so what is dropped does not depend on the threads' timing); 16 kB chunks so that a cut
    leaves several whole."""
    path = tmp_path_factory.mktemp("recordings") / "flight-20261125-101500.mcap"
    writer = RecordingWriter(path, RecorderOptions(chunk_kb=16, camera_queue=200),
                             metadata={"version": "0.1.0", "config": "[flight]\nspeed = 1\n"},
                             free_bytes=lambda directory: 10**15)
    writer.add_channel("/camera/image", fm.CompressedImage.get_schema(), droppable=True)
    writer.add_channel("/imu", IMU)
    writer.add_channel("/flight/events", fm.Log.get_schema())
    held, release = threading.Event(), threading.Event()
    writer.put("/imu", START_NS, lambda: held.set() or release.wait(10) and b"{}")
    assert held.wait(10)
    for k in range(1, 600):
        t = START_NS + k * STEP_NS
        if k == 1:
            writer.put("/flight/events", t, lambda: log(fm.LogLevel.Info, "ground -> takeoff: go"))
        elif k == 590:
            writer.put("/flight/events", t, lambda: log(fm.LogLevel.Warning,
                                                        "navigate -> failsafe_stop: depth stale"))
        elif k % 3 == 0 or k == 2:
            data = os.urandom(600)
            writer.put("/camera/image", t, lambda data=data: fm.CompressedImage(
                format="jpeg", data=data).encode())
        else:
            writer.put("/imu", t, lambda k=k: json.dumps({"t": k}).encode())
    for k in range(2):  # the queue holds 200 images: these two are dropped
        writer.put("/camera/image", START_NS + 3, lambda: b"")
    release.set()
    stats = writer.close()
    assert stats.dropped == {"/camera/image": {"queue full": 2}}
    return path


def info(capsys, *args) -> tuple[int, str, str]:
    code = main(["log", "info", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def test_info_summarises_a_complete_recording(recording, capsys):
    code, out, err = info(capsys, recording)
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0] == "flight-20261125-101500.mcap: complete"
    assert lines[1].startswith("  6.0 s, 600 messages,")
    assert "metadata: version=0.1.0, config" in out
    assert [line.split() for line in lines[3:7]] == [
        ["topic", "schema", "messages"],
        ["/camera/image", "foxglove.CompressedImage", "200"],
        ["/flight/events", "foxglove.Log", "2"],
        ["/imu", "companion.ImuSample", "398"]]
    assert "dropped: /camera/image 2 (queue full)" in out
    assert "events: 2, failsafes: 1" in out
    assert "0.01 s  info     ground -> takeoff: go" in out
    assert "5.90 s  warning  navigate -> failsafe_stop: depth stale" in out


def test_info_json_has_the_same_summary(recording, capsys):
    code, out, _ = info(capsys, recording, "--json")
    summary = json.loads(out)
    assert code == 0 and summary["complete"] is True and summary["messages"] == 600
    assert summary["duration_s"] == pytest.approx(5.99)
    assert {c["topic"]: c["messages"] for c in summary["channels"]} == {
        "/camera/image": 200, "/flight/events": 2, "/imu": 398}
    assert summary["metadata"] == {"version": "0.1.0", "config": "[flight]\nspeed = 1\n"}
    assert summary["recorder"]["dropped"] == {"/camera/image": {"queue full": 2}}
    assert summary["recorder"]["written"]["/imu"] == 398 and summary["recorder"]["error"] == ""
    assert summary["failsafes"] == 1
    assert [e["level"] for e in summary["events"]] == ["info", "warning"]


def in_file_order(path) -> list[tuple[str, int, bytes]]:
    with open(path, "rb") as file:
        return [(channel.topic, message.log_time, message.data) for _, channel, message
                in make_reader(file).iter_messages(log_time_order=False)]


@pytest.fixture
def cut(recording, tmp_path):
    """The recording as a power cut half way through would leave it, and the messages of the
    chunks the cut left whole, in file order (read from the complete file by its chunk index)."""
    with open(recording, "rb") as file:
        chunks = make_reader(file).get_summary().chunk_indexes
        cut_at = chunks[len(chunks) // 2].chunk_start_offset + 100  # inside a chunk
        whole = 0
        for chunk in chunks:
            if chunk.chunk_start_offset + chunk.chunk_length <= cut_at:
                file.seek(chunk.chunk_start_offset + 9)  # past the opcode and length
                whole += sum(isinstance(record, Message) for record in
                             breakup_chunk(Chunk.read(ReadDataStream(file))))
    path = tmp_path / "cut.mcap"
    path.write_bytes(recording.read_bytes()[:cut_at])
    return path, in_file_order(recording)[:whole]


def test_info_reads_a_truncated_recording_up_to_its_last_whole_chunk(cut, capsys):
    path, readable = cut
    whole = len(readable)
    code, out, err = info(capsys, path)
    assert code == 0, err
    assert out.startswith("cut.mcap: truncated: the file ends before its summary")
    assert f", {whole} messages," in out
    assert "recorder: no final counters" in out
    assert f"'companion log recover {path} OUT'" in out
    summary = json.loads(info(capsys, path, "--json")[1])
    assert summary["complete"] is False and summary["messages"] == whole
    assert summary["metadata"]["version"] == "0.1.0" and summary["recorder"] is None


def test_recover_writes_every_readable_message_into_a_complete_file(cut, tmp_path, capsys):
    path, readable = cut
    out_path = tmp_path / "recovered.mcap"
    assert main(["log", "recover", str(path), str(out_path)]) == 0
    assert capsys.readouterr().out == (f"{out_path}: {len(readable)} messages from {path} "
                                       "(truncated)\n")
    assert in_file_order(out_path) == readable
    summary = json.loads(info(capsys, out_path, "--json")[1])
    assert summary["complete"] is True and summary["metadata"]["version"] == "0.1.0"
    assert main(["log", "recover", str(path), str(out_path)]) == 1  # never overwrites
    assert capsys.readouterr().err == f"log recover: {out_path}: exists already; name a new file\n"


@pytest.mark.parametrize("content, error", [
    (None, "No such file or directory"),
    (b"", "empty, a recording that never began"),
    (b"[flight]\nspeed = 1\n", "not an MCAP file"),
])
def test_a_missing_or_foreign_file_is_one_line_and_exit_1(tmp_path, capsys, content, error):
    path = tmp_path / "flight.mcap"
    if content is not None:
        path.write_bytes(content)
    code, out, err = info(capsys, path)
    assert (code, out, err) == (1, "", f"log info: {path}: {error}\n")
    assert main(["log", "recover", str(path), str(tmp_path / "out.mcap")]) == 1
    assert capsys.readouterr().err == f"log recover: {path}: {error}\n"
    assert not (tmp_path / "out.mcap").exists()


def test_log_time_says_why_the_vehicle_flew_a_slower_tier(tmp_path, capsys):
    """Each plan records, for every faster tier that had nothing safe, how many of its arcs an
    observed surface blocked and how many met only unseen space; `log time` gives the median
    share blocked per tier, over the rounds it failed (docs/recording.md)."""
    from autonomy.navigation.mission import FlightState, Transition
    from companion.recording import topics

    path = tmp_path / "flight.mcap"
    writer = RecordingWriter(path, RecorderOptions(), metadata={},
                             free_bytes=lambda directory: 10**15)
    for topic in (topics.EVENTS, topics.PLAN):
        writer.add_channel(topic.name, topic.schema)
    states = [FlightState.ENTERING_OFFBOARD, FlightState.NAVIGATING, FlightState.LANDING]
    for k, (source, target) in enumerate(zip(states, states[1:])):
        transition = Transition(10.0 * k, source, target, "test")
        writer.put(topics.EVENTS.name, START_NS + k * 10**10,
                   lambda transition=transition: topics.encode_transition(transition))
    # the first round's faster tier is the middle one (the fastest too long to stop in)
    faster = [[(1.0, 50, 25)], [], [(2.0, 60, 15)], [(2.0, 30, 45)], [(2.0, 75, 0)]]
    for k, tiers in enumerate(faster):
        record = {"t": 1.0 + k, "kind": "arc", "reason": "", "speed": 0.5,
                  "faster": [{"speed": s, "blocked": b, "unseen": u} for s, b, u in tiers]}
        writer.put(topics.PLAN.name, START_NS + (1 + k) * 10**9,
                   lambda record=record: json.dumps(record).encode())
    writer.close()

    assert main(["log", "time", str(path), "--json"]) == 0
    spent = json.loads(capsys.readouterr().out)
    assert spent["faster_tiers"] == {"2.0 m/s": {"rounds": 3, "blocked_share": 0.8},
                                     "1.0 m/s": {"rounds": 1, "blocked_share": 50 / 75}}
    assert list(spent["faster_tiers"]) == ["2.0 m/s", "1.0 m/s"]  # fastest first
    assert main(["log", "time", str(path)]) == 0
    table = capsys.readouterr().out
    assert "why not faster" in table and "80%  2.0 m/s" in table


@pytest.mark.parametrize("faster, words", [
    ([{"speed": 2.0, "blocked": "many", "unseen": 0}], "faster record whose 'blocked' is 'many'"),
    (7, "/planner/plan record whose 'faster' is 7"),
])
def test_log_time_refuses_a_plan_whose_faster_tiers_are_malformed(tmp_path, capsys, faster,
                                                                  words):
    from companion.recording import topics

    path = tmp_path / "flight.mcap"
    writer = RecordingWriter(path, RecorderOptions(), metadata={},
                             free_bytes=lambda directory: 10**15)
    writer.add_channel(topics.PLAN.name, topics.PLAN.schema)
    record = {"t": 1.0, "kind": "arc", "reason": "", "faster": faster}
    writer.put(topics.PLAN.name, START_NS, lambda: json.dumps(record).encode())
    writer.close()
    assert main(["log", "time", str(path)]) == 1
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1
