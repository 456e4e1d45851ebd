"""The recorder's writer: one thread that owns the MCAP file, fed by bounded queues that never
block the flight (DESIGN.md, "Recording and replay"; docs/recording.md).

:meth:`RecordingWriter.put` is all the flight pays: an append to a bounded deque and, when the
writer sleeps, one wake-up. The message's ``encode`` (JPEG compression, protobuf, JSON) runs
later on the writer's thread. Images (``droppable`` channels) wait in a short queue and are
dropped first, when the writer falls behind or the disk nears its reserve; everything else
waits in a long one. Every message that does not reach the file is counted with its reason in
:attr:`RecordingWriter.stats`; the flight never sees an exception from here.

Crash safety: the file is MCAP in zstd-compressed chunks of ``[recorder] chunk_kb``. Each
chunk, once complete, is flushed and fsync'd, and a chunk is closed at least every
:data:`SYNC_S` seconds, so a SIGKILL or a power cut loses at most the chunk in progress and
the messages still queued; the rest is read back by ``companion log info`` and made a complete
file again by ``companion log recover``. zstd rather than lz4: neither compresses the JPEG
images, but zstd compresses the depth images and the JSON, which lz4 barely does; its cost is
the writer thread's, which keeps up at 20 Hz (docs/benchmarks.md, "Flight recorder").
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Callable, Mapping

import foxglove
from mcap.writer import CompressionType, Writer

from companion.recording.options import RecorderOptions
from companion.recording.storage import RecordingError, free_bytes_at

log = logging.getLogger(__name__)

#: Why a message is not in the file (the keys of ``RecordingStats.dropped[topic]``).
QUEUE_FULL = "queue full"  # the writer fell behind: its queue for the topic was full
DISK_RESERVE = "disk reserve"  # an image while the disk had less than reserve_mb free
WRITE_FAILED = "write failed"  # the file stopped at an error (a full disk, an I/O error)
BAD_MESSAGE = "bad message"  # a bug: no channel, a bad time, or its encode() raised
AFTER_CLOSE = "after close"  # put after close()

#: The longest a message waits in an open chunk before it is on disk, seconds.
SYNC_S = 1.0
#: How long a free-space reading serves before the disk is asked again, seconds.
FREE_SPACE_CHECK_S = 0.5
#: Metadata record names: what the caller gives (config, version, vehicle), the final counters.
COMPANION_METADATA, STATS_METADATA = "companion", "recording_stats"
#: MCAP message encoding of each schema encoding the recorder's topics use.
MESSAGE_ENCODINGS = {"protobuf": "protobuf", "jsonschema": "json"}


@dataclass(frozen=True)
class RecordingStats:
    """What a recording holds and what it lost. ``written`` counts messages per topic that are
    on disk (in a completed, fsync'd chunk); ``dropped`` counts the others per topic and reason;
    ``error`` is the write error that stopped the file, empty when none did."""

    written: dict[str, int] = field(default_factory=dict)
    dropped: dict[str, dict[str, int]] = field(default_factory=dict)
    bytes_written: int = 0
    error: str = ""

    def to_metadata(self) -> dict[str, str]:
        """The ``recording_stats`` record of the file: MCAP metadata values are strings."""
        return {"written": json.dumps(self.written), "dropped": json.dumps(self.dropped),
                "error": self.error}


Encode = Callable[[], bytes]
Sink = Callable[[str, int, bytes], None]


class RecordingWriter:
    """Writes one recording at ``path`` (made by :func:`~companion.recording.storage.prepare`)
    on its own daemon thread until :meth:`close`.

    ``metadata`` (string values) goes into the file as the ``companion`` record. ``free_bytes``
    tells the free space of a directory (the real disk's by default; tests pass their own).
    Raises :class:`~companion.recording.storage.RecordingError` when the file cannot be opened
    or begun, before anything flies.
    """

    def __init__(self, path: Path, options: RecorderOptions, *,
                 metadata: Mapping[str, str] | None = None,
                 free_bytes: Callable[[Path], int] = free_bytes_at):
        self.path, self.options = Path(path), options
        metadata = dict(metadata or {})
        wrong = [key for key, value in metadata.items() if not isinstance(value, str)]
        if wrong:
            raise ValueError(f"recording metadata values must be strings; {wrong[0]!r} is "
                             f"{type(metadata[wrong[0]]).__name__}")
        self._free_bytes, self._reserve = free_bytes, options.reserve_mb * 1_000_000
        self._free_checked, self._below_reserve = -float("inf"), False
        self._droppable: dict[str, bool] = {}
        self._new_channels: deque[tuple[str, foxglove.Schema]] = deque()
        self._channel_ids: dict[str, int] = {}
        self._schema_ids: dict[tuple[str, str, bytes], int] = {}
        self._images: deque[tuple[str, int, Encode, int]] = deque()
        self._events: deque[tuple[str, int, Encode, int]] = deque()
        self._sinks: list[Sink] = []
        self._lock = threading.Lock()  # the counters, read by stats from any thread
        self._written: Counter[str] = Counter()
        self._in_chunk: Counter[str] = Counter()  # written to the open chunk, not yet on disk
        self._dropped: dict[str, Counter[str]] = {}
        self._bytes, self._error = 0, ""
        self._wake = threading.Event()
        self._sync_at = time.monotonic() + SYNC_S  # when the open chunk goes to disk at the latest
        self._closing = self._closed = False
        self._close_lock = threading.Lock()
        self._file, self._mcap = self._begin(metadata)
        self._thread = threading.Thread(target=self._run, name="recording-writer", daemon=True)
        self._thread.start()

    def _begin(self, metadata: dict[str, str]) -> tuple[BinaryIO, Writer]:
        """Open the file and write its header and the caller's metadata, on disk at once."""
        try:
            file = open(self.path, "wb")
        except OSError as error:
            raise RecordingError(f"cannot write the recording {self.path}: "
                                 f"{error.strerror or error}") from None
        try:
            mcap = Writer(file, chunk_size=self.options.chunk_kb * 1000,
                          compression=CompressionType.ZSTD)
            mcap.start()
            mcap.add_metadata(COMPANION_METADATA, metadata)
            file.flush()
            os.fsync(file.fileno())
        except OSError as error:
            file.close()
            raise RecordingError(f"cannot write the recording {self.path}: "
                                 f"{error.strerror or error}") from None
        self._bytes = file.tell()
        return file, mcap

    # The caller's side, from any thread.

    def add_channel(self, topic: str, schema: foxglove.Schema, *, droppable: bool = False) -> None:
        """Declare ``topic`` before its first :meth:`put`; ``droppable`` (images) is dropped
        first when the writer falls behind or the disk nears its reserve. ValueError for a
        topic declared twice or a schema encoding MCAP readers would not know."""
        if topic in self._droppable:
            raise ValueError(f"the recording has a channel {topic} already")
        if schema.encoding not in MESSAGE_ENCODINGS:
            raise ValueError(f"{topic}: cannot record schema encoding {schema.encoding!r}; "
                             f"one of {', '.join(MESSAGE_ENCODINGS)}")
        self._new_channels.append((topic, schema))
        self._droppable[topic] = droppable

    def put(self, topic: str, t_ns: int, encode: Encode, publish_ns: int | None = None) -> None:
        """Record ``encode()`` on ``topic`` logged at ``t_ns`` (nanoseconds on the companion's
        clock: when the flight handled it) and published at ``publish_ns`` (when it was
        measured, a frame's exposure say; default ``t_ns``). ``encode`` runs later, on the
        writer's thread; ``put`` only queues it, or counts it dropped when its queue is full.
        Never blocks, never raises."""
        droppable = self._droppable.get(topic)
        if self._closing:
            self._drop(topic, AFTER_CLOSE)
            return
        if droppable is None:
            self._drop(topic, BAD_MESSAGE, f"no channel {topic}: put before add_channel")
            return
        queue = self._images if droppable else self._events
        if len(queue) >= (self.options.camera_queue if droppable else self.options.event_queue):
            self._drop(topic, QUEUE_FULL)
            return
        queue.append((topic, t_ns, encode, t_ns if publish_ns is None else publish_ns))
        if not self._wake.is_set():
            self._wake.set()

    def add_sink(self, sink: Sink) -> None:
        """Hand every encoded message, ``sink(topic, t_ns, data)``, to ``sink`` too (the live
        view), on the writer's thread: it must return quickly. A sink that raises is logged and
        removed; images a full disk keeps from the file still reach it."""
        self._sinks.append(sink)

    @property
    def stats(self) -> RecordingStats:
        """The counters now (the final ones after :meth:`close`)."""
        with self._lock:
            return RecordingStats(
                written=dict(self._written),
                dropped={topic: dict(reasons) for topic, reasons in self._dropped.items()},
                bytes_written=self._bytes, error=self._error)

    def close(self) -> RecordingStats:
        """Write what is queued, the counters (the ``recording_stats`` record) and the MCAP
        summary, close the file and stop the thread; the final :attr:`stats`. Idempotent."""
        with self._close_lock:
            if not self._closed:
                self._closing = True
                self._wake.set()
                self._thread.join()
                self._closed = True
                for topic, *_ in (*self._events, *self._images):  # queued as it closed
                    self._drop(topic, AFTER_CLOSE)
        return self.stats

    def _drop(self, topic: str, reason: str, why: str = "") -> None:
        with self._lock:
            reasons = self._dropped.setdefault(topic, Counter())
            reasons[reason] += 1
            first = reasons[reason] == 1
        if first and reason != WRITE_FAILED:  # that one is logged once for the whole file
            log.warning("recording %s: dropping %s (%s%s); every drop is counted in the "
                        "recording's stats", self.path.name, topic, reason,
                        f": {why}" if why else "")

    # The writer's thread.

    def _run(self) -> None:
        while True:
            self._wake.wait(max(0.0, self._sync_at - time.monotonic()))
            self._wake.clear()  # before draining: a put from now on wakes the next round
            closing = self._closing
            self._drain()
            self._end_chunk_if_due()
            if closing:
                break
        self._finish()

    def _drain(self) -> None:
        """Write everything queued: all waiting events before each image, so a slow JPEG
        never holds the IMU back."""
        while self._events or self._images:
            while self._events:
                self._handle(*self._events.popleft(), droppable=False)
            if self._images:
                self._handle(*self._images.popleft(), droppable=True)
            self._end_chunk_if_due()

    def _handle(self, topic: str, t_ns: int, encode: Encode, publish_ns: int, *,
                droppable: bool) -> None:
        """Encode one message and hand it to the file and the sinks; count it dropped from
        the file when the file has failed or, for an image, the disk is below its reserve."""
        for stamp in (t_ns, publish_ns):
            if not (isinstance(stamp, int) and 0 <= stamp < 1 << 64):
                self._drop(topic, BAD_MESSAGE,
                           f"time {stamp!r} is not unsigned 64-bit nanoseconds")
                return
        lost = (WRITE_FAILED if self._error
                else DISK_RESERVE if droppable and self._disk_below_reserve() else "")
        if lost:
            self._drop(topic, lost)
            if not self._sinks:
                return
        try:
            data = encode()
            if not isinstance(data, (bytes, bytearray, memoryview)):
                raise TypeError(f"returned {type(data).__name__}, not bytes")
        except Exception as error:  # a bug in one encoder must not stop the recording
            log.debug("encoding %s failed", topic, exc_info=True)
            if not lost:
                self._drop(topic, BAD_MESSAGE, f"encode() failed: {error!r}")
            return
        if not lost:
            self._write(topic, t_ns, data, publish_ns)
        self._send(topic, t_ns, data)

    def _write(self, topic: str, t_ns: int, data: bytes, publish_ns: int) -> None:
        try:
            before = self._file.tell()
            channel = self._channel_id(topic)
            with self._lock:
                self._in_chunk[topic] += 1
            self._mcap.add_message(channel, t_ns, data, publish_ns)
            if self._file.tell() != before:  # the writer completed a chunk
                self._sync()
        except Exception as error:  # whatever stopped it, the file ends at its last chunk
            self._fail(error)

    def _channel_id(self, topic: str) -> int:
        """``topic``'s MCAP channel, registering every channel declared since the last."""
        while self._new_channels:
            name, schema = self._new_channels.popleft()
            key = (schema.name, schema.encoding, bytes(schema.data))
            if key not in self._schema_ids:
                self._schema_ids[key] = self._mcap.register_schema(*key)
            self._channel_ids[name] = self._mcap.register_channel(
                name, MESSAGE_ENCODINGS[schema.encoding], self._schema_ids[key])
        return self._channel_ids[topic]

    def _send(self, topic: str, t_ns: int, data: bytes) -> None:
        for sink in tuple(self._sinks):
            try:
                sink(topic, t_ns, data)
            except Exception:  # a failing viewer must not stop the recording
                log.exception("recording %s: removed the sink %r, which raised",
                              self.path.name, sink)
                self._sinks.remove(sink)

    def _disk_below_reserve(self) -> bool:
        now = time.monotonic()
        if now - self._free_checked >= FREE_SPACE_CHECK_S:
            self._free_checked = now
            try:
                below = self._free_bytes(self.path.parent) < self._reserve
            except OSError:  # the directory is gone: the next write says why
                below = True
            if below != self._below_reserve:
                log.warning("recording %s: %s", self.path.name,
                            "the disk is below [recorder] reserve_mb: images are no longer "
                            "recorded" if below else "the disk is above the reserve again: "
                            "recording images")
            self._below_reserve = below
        return self._below_reserve

    def _end_chunk_if_due(self) -> None:
        """Put the open chunk on disk when its oldest message may be :data:`SYNC_S` old."""
        if time.monotonic() >= self._sync_at:
            self._end_chunk()
            self._sync_at = time.monotonic() + SYNC_S

    def _end_chunk(self) -> None:
        """Close the open chunk and put it on disk, when it holds anything."""
        if self._in_chunk and not self._error:
            try:
                self._mcap.flush()
                self._sync()
            except Exception as error:
                self._fail(error)

    def _sync(self) -> None:
        """What the file was given is on disk: count the open chunk's messages written."""
        self._file.flush()
        os.fsync(self._file.fileno())
        with self._lock:
            self._written.update(self._in_chunk)
            self._in_chunk.clear()
            self._bytes = self._file.tell()
        self._sync_at = time.monotonic() + SYNC_S

    def _fail(self, error: Exception) -> None:
        """Stop the file at ``error``: the open chunk's messages and all later ones are
        dropped (``write failed``); the file stays readable up to its last complete chunk."""
        text = (f"{error.strerror} (errno {error.errno})"
                if isinstance(error, OSError) and error.strerror else repr(error))
        log.error("recording %s stopped: %s; the flight goes on unrecorded", self.path, text,
                  exc_info=not isinstance(error, OSError))
        with self._lock:
            self._error = text
            for topic, count in self._in_chunk.items():
                self._dropped.setdefault(topic, Counter())[WRITE_FAILED] += count
            self._in_chunk.clear()

    def _finish(self) -> None:
        """Last chunk, the counters, the summary and footer; then close the file."""
        self._end_chunk()
        if not self._error:
            try:
                self._mcap.add_metadata(STATS_METADATA, self.stats.to_metadata())
                self._mcap.finish()
                self._sync()
            except Exception as error:
                self._fail(error)
        try:
            self._file.close()
        except OSError:  # after a failed write the buffer cannot be flushed: it is dropped
            pass
