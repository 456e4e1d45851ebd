"""One flight's recording, from before arming to after landing (docs/recording.md).

:func:`open_recording` is called before the flight starts, so a recording that cannot be made
(no writable directory, a full disk) is a clear :class:`~companion.recording.storage.
RecordingError` while the vehicle is still on the ground; :meth:`Recording.attach` taps the
application; :meth:`Recording.close` finishes the file and returns what the summary says of it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from companion import __version__
from companion.config import dump_toml
from companion.recording.live import LiveView, parse_address
from companion.recording.options import RecorderOptions
from companion.recording.recorder import FlightRecorder
from companion.recording.storage import RecordingError, prepare
from companion.recording.writer import RecordingWriter


@dataclass
class Recording:
    """The file, its writer, the taps on one flight, and the live view when one is served."""

    path: Path
    writer: RecordingWriter
    recorder: FlightRecorder
    live: LiveView | None = None

    def attach(self, app) -> None:
        self.recorder.attach(app)

    def close(self) -> dict:
        """Detach, finish the file, stop the live view, and say what the file holds: the
        summary's ``recording``. Idempotent."""
        self.recorder.detach()
        stats = self.writer.close()
        if self.live is not None:
            self.live.close()
        return {"path": str(self.path), "messages": sum(stats.written.values()),
                "bytes": stats.bytes_written, "dropped": stats.dropped,
                "error": stats.error or None}


def open_recording(options: RecorderOptions, *, clock, metadata: dict[str, str],
                   to_file: bool = True, live: str | None = None) -> Recording | None:
    """A new recording in ``[recorder] directory`` (the oldest flights removed to keep the
    quota), served live on ``live`` (``HOST:PORT``) too when given; None when neither is
    wanted. ``metadata`` (the config, the mission) goes into the file beside the flight.
    RecordingError (or LiveViewError) says what to fix, before anything flies."""
    if not to_file and live is None:
        return None
    if not to_file:
        raise RecordingError("--live serves what the recorder writes: it needs recording on "
                             "(drop --no-record, or set [recorder] enabled = true)")
    view = LiveView(*parse_address(live)) if live is not None else None
    try:
        path = prepare(options)
        writer = RecordingWriter(path, options, metadata=metadata)
    except BaseException:
        if view is not None:
            view.close()
        raise
    if view is not None:
        writer.add_sink(view.sink)
    recorder = FlightRecorder(writer, clock, camera_format=options.camera_format,
                              jpeg_quality=options.jpeg_quality)
    return Recording(path, writer, recorder, view)


async def recorded(app, recording: Recording | None) -> dict:
    """``app.run()``, recorded when ``recording`` is given: the summary then says where the
    file is, what it holds and what was dropped (``recording``)."""
    if recording is None:
        return await app.run()
    recording.attach(app)
    try:
        summary = await app.run()
    finally:
        closed = recording.close()
    summary["recording"] = closed
    return summary


def recording_metadata(config, **extra: str) -> dict[str, str]:
    """What a recording keeps beside the flight: the effective config as TOML (what replay
    starts from), the software version, and ``extra`` (the simulated mission, say)."""
    return {"config": dump_toml(config), "version": __version__, **extra}
