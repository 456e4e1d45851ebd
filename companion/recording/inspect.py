"""What a recording holds, and a truncated recording made whole again (``companion log info``
and ``companion log recover``; docs/recording.md).

A complete file is summarised from its MCAP summary (message counts, metadata) and the chunks
that hold flight events, without reading the images. A file without a summary (the process was
killed, the power cut, the disk filled) is read from the start as far as its chunks are
complete: that is what :func:`recover` rewrites as a complete file.
"""

from __future__ import annotations

import json
import struct
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Channel, Footer, Header, McapRecord, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from mcap_protobuf.decoder import DecoderFactory

from companion.recording.writer import COMPANION_METADATA, STATS_METADATA

MCAP_MAGIC = b"\x89MCAP0\r\n"
#: The flight's state transitions (foxglove Log messages); the failsafes are those at warning
#: level or above (companion.recording.topics.encode_transition).
EVENTS_TOPIC = "/flight/events"
#: foxglove.LogLevel numbers -> names.
LOG_LEVELS = ("unknown", "debug", "info", "warning", "error", "fatal")
WARNING = LOG_LEVELS.index("warning")
#: Events listed in the text summary (a flight has a few dozen; --json has them all).
MAX_EVENT_LINES = 100


class InspectError(Exception):
    """The file is not a recording that can be read, or the output cannot be written; the
    message names the file."""


@dataclass
class _Contents:
    """What a pass over a recording found, whichever way it was read."""

    channels: dict[int, Channel] = field(default_factory=dict)
    schemas: dict[int, Schema] = field(default_factory=dict)
    counts: Counter[int] = field(default_factory=Counter)
    start_ns: int | None = None
    end_ns: int | None = None
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    events: list[tuple[int, Schema | None, Channel, Message]] = field(default_factory=list)

    def add_message(self, message: Message) -> None:
        self.counts[message.channel_id] += 1
        t = message.log_time
        self.start_ns = t if self.start_ns is None else min(self.start_ns, t)
        self.end_ns = t if self.end_ns is None else max(self.end_ns, t)
        channel = self.channels.get(message.channel_id)
        if channel is not None and channel.topic == EVENTS_TOPIC:
            self.events.append((t, self.schemas.get(channel.schema_id), channel, message))


class _Readable:
    """Every record a stream reader gets from the start of a file, in file order, up to the
    first it cannot read. After iterating, ``complete`` says whether that was the footer, and
    ``stopped`` says why reading stopped before it."""

    def __init__(self, path: Path):
        self.path, self.complete, self.stopped = path, False, ""

    def __iter__(self) -> Iterator[McapRecord]:
        with open(self.path, "rb") as file:
            try:
                for record in StreamReader(file, validate_crcs=True).records:
                    self.complete = isinstance(record, Footer)
                    yield record
            except Exception as error:  # any unreadable byte is where the file was cut
                self.stopped = _why(error)


def _why(error: Exception) -> str:
    """Why a stream reading stopped, for a person: the file simply ends (a kill, a power cut,
    a full disk), or a record is damaged."""
    if isinstance(error, (EndOfFile, struct.error)):
        return "the file ends before its summary"
    return f"a damaged record ({type(error).__name__}: {error})"


def check_file(path: Path) -> None:
    """Raise :class:`InspectError` unless ``path`` is a file that begins as MCAP does."""
    try:
        with open(path, "rb") as file:
            magic = file.read(len(MCAP_MAGIC))
    except OSError as error:
        raise InspectError(f"{path}: {error.strerror or error}") from None
    if not magic:
        raise InspectError(f"{path}: empty, a recording that never began")
    if magic != MCAP_MAGIC:
        raise InspectError(f"{path}: not an MCAP file")


def summarise(path: Path) -> dict:
    """The recording at ``path`` as a JSON-able dict: whether it is complete, its duration
    (first to last message), each channel's topic, schema and message count, the ``companion``
    metadata, the recorder's own counters (``recorder``, None when the file was cut short), and
    the flight events with the count of failsafes among them."""
    path = Path(path)
    check_file(path)
    contents, complete, stopped = _from_summary(path) or _from_stream(path)
    events = _events(contents)
    start, end = contents.start_ns, contents.end_ns
    return {
        "path": str(path), "complete": complete, "stopped": stopped,
        "bytes": path.stat().st_size,
        "duration_s": 0.0 if start is None else (end - start) / 1e9,
        "messages": sum(contents.counts.values()),
        "channels": sorted(({
            "topic": channel.topic,
            "schema": getattr(contents.schemas.get(channel.schema_id), "name", ""),
            "messages": contents.counts[channel_id]}
            for channel_id, channel in contents.channels.items()),
            key=lambda channel: channel["topic"]),
        "metadata": contents.metadata.get(COMPANION_METADATA, {}),
        "recorder": _recorder_stats(contents.metadata.get(STATS_METADATA)),
        "events": events,
        "failsafes": sum(event["level"] in LOG_LEVELS[WARNING:] for event in events),
    }


def _from_summary(path: Path) -> tuple[_Contents, bool, str] | None:
    """A complete file's contents from its summary and its events' chunks; None when the file
    has no readable summary (then it is read as a stream)."""
    with open(path, "rb") as file:
        try:
            reader = make_reader(file, validate_crcs=True)
            summary = reader.get_summary()
            if summary is None or summary.statistics is None:
                return None
            contents = _Contents(channels=dict(summary.channels),
                                 schemas=dict(summary.schemas),
                                 counts=Counter(summary.statistics.channel_message_counts))
            if summary.statistics.message_count:
                contents.start_ns = summary.statistics.message_start_time
                contents.end_ns = summary.statistics.message_end_time
            contents.metadata = {record.name: record.metadata
                                 for record in reader.iter_metadata()}
            contents.events = [(message.log_time, schema, channel, message)
                               for schema, channel, message in reader.iter_messages(
                                   topics=[EVENTS_TOPIC], log_time_order=True)]
        except Exception:  # a damaged summary or index: the stream reading says what is there
            return None
    return contents, True, ""


def _from_stream(path: Path) -> tuple[_Contents, bool, str]:
    contents, readable = _Contents(), _Readable(path)
    for record in readable:
        if isinstance(record, Message):
            contents.add_message(record)
        elif isinstance(record, Channel):
            contents.channels.setdefault(record.id, record)
        elif isinstance(record, Schema):
            contents.schemas.setdefault(record.id, record)
        elif isinstance(record, Metadata):
            contents.metadata[record.name] = record.metadata
    return contents, readable.complete, readable.stopped


def _events(contents: _Contents) -> list[dict]:
    """The flight events in time order: seconds into the recording, level and text."""
    decoders = DecoderFactory()
    return [_event(decoders, contents.start_ns, *event)
            for event in sorted(contents.events, key=lambda event: event[0])]


def _event(decoders: DecoderFactory, start_ns: int, t_ns: int, schema: Schema | None,
           channel: Channel, message: Message) -> dict:
    try:
        log = decoders.decoder_for(channel.message_encoding, schema)(message.data)
        level = LOG_LEVELS[log.level] if 0 <= log.level < len(LOG_LEVELS) else "unknown"
        text = log.message
    except Exception:  # not a foxglove Log: counted, not read
        level, text = "unknown", "(not decodable)"
    return {"t_s": (t_ns - start_ns) / 1e9, "level": level, "text": text}


def _recorder_stats(record: dict[str, str] | None) -> dict | None:
    """The recorder's final counters (``recording_stats``), as written by
    :meth:`~companion.recording.writer.RecordingStats.to_metadata`."""
    if record is None:
        return None
    try:
        return {"written": json.loads(record.get("written", "{}")),
                "dropped": json.loads(record.get("dropped", "{}")),
                "error": record.get("error", "")}
    except json.JSONDecodeError:
        return {"written": {}, "dropped": {}, "error": "unreadable recording_stats record"}


def format_summary(summary: dict) -> str:
    """The summary as a few lines for a person."""
    name = Path(summary["path"]).name
    state = ("complete" if summary["complete"] else
             f"truncated: {summary['stopped']}; read up to its last complete chunk")
    lines = [f"{name}: {state}",
             f"  {summary['duration_s']:.1f} s, {summary['messages']} messages, "
             f"{summary['bytes'] / 1e6:.1f} MB"]
    metadata = summary["metadata"]
    if metadata:
        lines.append("  metadata: " + ", ".join(
            f"{key}={value}" if len(value) <= 40 and "\n" not in value else key
            for key, value in metadata.items()))
    width = max([len(channel["topic"]) for channel in summary["channels"]] + [5])
    schema_width = max([len(channel["schema"]) for channel in summary["channels"]] + [6])
    lines.append(f"  {'topic':<{width}}  {'schema':<{schema_width}}  messages")
    lines += [f"  {c['topic']:<{width}}  {c['schema']:<{schema_width}}  {c['messages']:>8}"
              for c in summary["channels"]]
    lines += _format_recorder(summary["recorder"])
    events = summary["events"]
    lines.append(f"  events: {len(events)}, failsafes: {summary['failsafes']}")
    lines += [f"    {event['t_s']:8.2f} s  {event['level']:<7}  {event['text']}"
              for event in events[:MAX_EVENT_LINES]]
    if len(events) > MAX_EVENT_LINES:
        lines.append(f"    ... {len(events) - MAX_EVENT_LINES} more (--json lists them all)")
    if not summary["complete"]:
        lines.append(f"  'companion log recover {summary['path']} OUT' writes what is readable "
                     "as a complete file")
    return "\n".join(lines)


def _format_recorder(recorder: dict | None) -> list[str]:
    if recorder is None:
        return ["  recorder: no final counters (the recording was cut short)"]
    drops = [f"{topic} {count} ({reason})" for topic, reasons in recorder["dropped"].items()
             for reason, count in reasons.items()]
    lines = [f"  dropped: {', '.join(drops) if drops else 'none'}"]
    if recorder["error"]:
        lines.append(f"  write error: {recorder['error']}")
    return lines


def recover(source: Path, out: Path, *, chunk_kb: int = 1024) -> dict:
    """Write every readable message, channel and metadata record of ``source`` (truncated or
    not) into a new, complete MCAP file ``out``, which must not exist. Returns what it
    wrote: ``messages``, and whether the source was ``complete``."""
    source, out = Path(source), Path(out)
    check_file(source)
    if out.exists():
        raise InspectError(f"{out}: exists already; name a new file")
    readable = _Readable(source)
    try:
        with open(out, "xb") as file:
            messages = _copy(readable, Writer(file, chunk_size=chunk_kb * 1000,
                                              compression=CompressionType.ZSTD))
    except OSError as error:
        out.unlink(missing_ok=True)
        raise InspectError(f"{out}: {error.strerror or error}") from None
    return {"source": str(source), "out": str(out), "messages": messages,
            "complete": readable.complete, "stopped": readable.stopped}


def _copy(readable: _Readable, writer: Writer) -> int:
    """Copy ``readable``'s records into ``writer`` (renumbering schemas and channels); the
    number of messages."""
    schema_ids, channel_ids, messages = {0: 0}, {}, 0
    writer.start()
    for record in readable:
        if isinstance(record, Header):
            continue
        if isinstance(record, Schema) and record.id not in schema_ids:
            schema_ids[record.id] = writer.register_schema(record.name, record.encoding,
                                                           record.data)
        elif isinstance(record, Channel) and record.id not in channel_ids:
            channel_ids[record.id] = writer.register_channel(
                record.topic, record.message_encoding, schema_ids[record.schema_id],
                record.metadata)
        elif isinstance(record, Message):
            writer.add_message(channel_ids[record.channel_id], record.log_time, record.data,
                               record.publish_time, record.sequence)
            messages += 1
        elif isinstance(record, Metadata):
            writer.add_metadata(record.name, record.metadata)
    writer.add_metadata("recovery", {"complete": str(readable.complete).lower(),
                                     "stopped": readable.stopped, "messages": str(messages)})
    writer.finish()
    return messages
