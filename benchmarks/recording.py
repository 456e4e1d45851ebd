"""What the flight recorder costs the flight loop: loop lag with and without recording.

    python benchmarks/recording.py [--repeats 3] [--world dome]

Flies ``companion sim fly --world W --clock realtime --json --no-plot`` (the world's first
pair, estimated depth, the application's stages in worker threads on the wall clock, as on
the vehicle) in a child process, ``--repeats`` times recording into a temporary directory and
as many times with ``--no-record``, interleaved so both see the same machine load. Reports,
per mode, the medians over flights of the event loop's lag p99 (the summary's
``loop_lag_ms_p99``: how late the loop runs its timers, which is how late a setpoint can be),
the camera frames the flight saw, and for the recorded flights the frames the writer dropped
and the file's size per second of flight. First, in this process, what one tap costs the
thread that publishes (the flight's loop or a worker): microseconds per IMU sample and per
camera frame handed to a real writer, medians of ``--tap-repeats`` batches.
"""

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from autonomy.messages import Frame, ImuSample
from companion.recording.options import RecorderOptions
from companion.recording.recorder import FlightRecorder
from companion.recording.writer import RecordingWriter
from drivers.clock import MonotonicClock

#: Messages per timed batch of the tap benchmark.
TAP_BATCH = 200


def fly(world: str, recordings: Path | None) -> dict:
    """The summary of one realtime flight, recorded into ``recordings`` (None: not at all)."""
    record = ["--set", f"recorder.directory={recordings}"] if recordings else ["--no-record"]
    run = subprocess.run([sys.executable, "-m", "companion", "sim", "fly", "--world", world,
                          "--clock", "realtime", "--json", "--no-plot", *record],
                         capture_output=True, text=True)
    if not run.stdout:
        raise SystemExit(f"sim fly failed: {run.stderr[-2000:]}")
    return json.loads(run.stdout)


def describe(summaries: list[dict]) -> dict:
    def median(values):
        return round(statistics.median(values), 3)

    report = {"flights": len(summaries),
              "loop_lag_ms_p99": median([s["loop_lag_ms_p99"] for s in summaries]),
              "loop_lag_ms_p99_range": [round(min(s["loop_lag_ms_p99"] for s in summaries), 3),
                                        round(max(s["loop_lag_ms_p99"] for s in summaries), 3)],
              "frames": median([s["frames"] for s in summaries]),
              "reached_goal": sum(bool(s["reached_goal"]) for s in summaries)}
    recorded = [s["recording"] for s in summaries if "recording" in s]
    if recorded:
        report["camera_frames_dropped"] = median(
            [sum(r["dropped"].get("/camera/image", {}).values()) for r in recorded])
        report["megabytes_per_flight_second"] = median(
            [r["bytes"] / 1e6 / max(s["flight_time_s"], 1e-9)
             for r, s in zip(recorded, summaries)])
    return report


def tap_cost(repeats: int) -> dict:
    """Microseconds the publishing thread spends per message, IMU sample and camera frame."""
    imu = ImuSample(1.0, np.zeros(3), np.array([0.0, 0.0, 9.81]))
    frame = Frame(1.0, np.zeros((480, 640, 3), np.uint8))
    costs = {"imu_sample_us": [], "camera_frame_us": []}
    with tempfile.TemporaryDirectory() as directory:
        # queues large enough that nothing is dropped: the cost of queueing, not of dropping
        options = RecorderOptions(directory=directory, camera_queue=1000)
        writer = RecordingWriter(Path(directory) / "taps.mcap", options)
        recorder = FlightRecorder(writer, MonotonicClock())
        for _ in range(repeats):
            for key, tap, message in (("imu_sample_us", recorder._on_imu, imu),
                                      ("camera_frame_us", recorder._on_frame, frame)):
                start = time.perf_counter()
                for _ in range(TAP_BATCH):
                    tap(message)
                costs[key].append((time.perf_counter() - start) / TAP_BATCH * 1e6)
            time.sleep(0.5)  # let the writer drain: each batch meets empty queues
        writer.close()
    return {key: round(statistics.median(values), 2) for key, values in costs.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--world", default="dome")
    parser.add_argument("--tap-repeats", type=int, default=20)
    args = parser.parse_args()
    report = {"tap": tap_cost(args.tap_repeats)}
    flights = {"recording": [], "not_recording": []}
    with tempfile.TemporaryDirectory() as directory:
        for _ in range(args.repeats):
            flights["recording"].append(fly(args.world, Path(directory)))
            flights["not_recording"].append(fly(args.world, None))
    report.update({mode: describe(summaries) for mode, summaries in flights.items()})
    report["p99_added_ms"] = round(report["recording"]["loop_lag_ms_p99"]
                                   - report["not_recording"]["loop_lag_ms_p99"], 3)
    print(json.dumps(report))


if __name__ == "__main__":
    main()
