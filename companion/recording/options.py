"""The ``[recorder]`` table: where flights are recorded, how much disk they may take, and how
much the writer may hold back before it drops camera frames (docs/recording.md)."""

from __future__ import annotations

from dataclasses import dataclass

from autonomy.options import OptionError, option, validate


#: How the recorder stores camera images (``[recorder] camera_format``).
CAMERA_FORMATS = ("jpeg", "png")


@dataclass(frozen=True)
class RecorderOptions:
    """How every flight is recorded. Sizes are decimal: 1 kB = 1000 bytes, 1 MB = 10^6 bytes."""

    enabled: bool = option(True, doc="record every flight (`--no-record` turns it off for one "
                                     "run)")
    directory: str = option("recordings", doc="folder of the recordings; a relative path is "
                                              "relative to the working directory "
                                              "(/var/lib/companion under systemd)")
    quota_mb: float = option(20000.0, gt=0.0, doc="total size of the flights in `directory`, "
                                                  "MB; the oldest are deleted when a flight "
                                                  "starts to stay under it")
    reserve_mb: float = option(500.0, ge=0.0, doc="free disk space always left, MB: a flight "
                                                  "does not start below it, and in flight the "
                                                  "recorder stops writing images below it")
    chunk_kb: int = option(1024, ge=16, le=65536, doc="MCAP chunk size, kB: at most this much "
                                                      "(or the last second) is lost to a power "
                                                      "cut")
    camera_queue: int = option(16, ge=1, le=1000, doc="images waiting to be written (the "
                                                      "camera's and the depth's, 5 a frame); "
                                                      "more are dropped and counted")
    event_queue: int = option(100000, ge=100, le=10_000_000,
                              doc="other messages waiting to be written (IMU, events, poses); "
                                  "more are dropped and counted")
    camera_format: str = option("jpeg", choices=CAMERA_FORMATS,
                                doc="how camera images are stored: jpeg (about 50 kB a "
                                    "640x480 frame) or png (lossless, about 5 times larger: "
                                    "a replay then sees exactly the frames the flight saw)")
    jpeg_quality: int = option(90, ge=50, le=100, doc="JPEG quality of the recorded camera "
                                                      "images")

    def __post_init__(self) -> None:
        validate(self)
        if not self.directory.strip():
            raise OptionError("directory", "must name a folder, e.g. \"recordings\"")
