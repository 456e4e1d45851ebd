"""``companion fly``: the application on the real vehicle.

The same :class:`~companion.flight.app.FlightApp` the simulator flies, wired to real devices: the
flight controller over ``[mavlink] url`` (serial on the Orin's UART, or UDP), the camera
``[camera] driver`` names (V4L2, RealSense or OAK; its frames rectified with the calibration
``[camera] calibration`` names), the user's ONNX depth network of ``[depth_network]``
(required here: the synthetic stand-in needs a simulator's ground truth), the wall clock and
worker threads. The mission is ``[flight] waypoints`` (or ``--goal`` on the command line); it
starts only on the operator's go (``[go]``, :mod:`companion.flight.go`).

Run by systemd (``systemd/companion.service``, Type=notify): more start-up time asked for while
the network opens (a first TensorRT engine build), ``READY=1`` once preflight has passed, ``WATCHDOG=1`` from the event loop's monitor (a stalled loop stops the pings and systemd
restarts the service), ``STOPPING=1`` at the end; SIGTERM or SIGINT ask the mission to stop,
which in the air means stop, hold and land. With ``[camera] learned_time_offset_file`` and
``learned_gyro_alignment_file`` the camera-IMU time offset and the gyro's yaw response a flight
estimated are the next flight's start (:mod:`companion.launch.learned_calibration`).
"""

from __future__ import annotations

import asyncio
import logging
import signal

from autonomy.depth.network import DepthNetwork
from companion.flight.app import FlightApp
from companion.flight.perception import NetworkDepth
from companion.launch.learned_calibration import keep_learned, start_from_learned
from companion.launch.systemd import SystemdNotifier
from companion.recording.session import open_recording, recorded, recording_metadata
from drivers.camera.calibration import CalibratedCamera, grid_stamps, resolve
from drivers.camera.drivers import open_camera
from drivers.clock import MonotonicClock
from drivers.mavlink.autopilot import Autopilot
from drivers.mavlink.signing import load_key

log = logging.getLogger(__name__)


class FlyError(RuntimeError):
    """The real flight cannot start; the message says what to fix."""


def run(config, waypoints, *, record: bool = True, live: str | None = None) -> dict:
    """Fly ``waypoints`` ((x, y, z) tuples in PX4's local frame, ENU) and return the summary;
    ``record``: into an MCAP file as ``[recorder]`` says, ``live``: served to Foxglove on
    ``HOST:PORT`` (docs/recording.md). A signing key that cannot be used is a
    :class:`~drivers.mavlink.signing.SigningKeyError` before anything opens."""
    if not waypoints:
        raise FlyError("no mission: set [flight] waypoints in the config or give --goal X,Y,Z")
    if not config.depth_network.model:
        raise FlyError("[depth_network] model is empty: companion fly needs the ONNX depth "
                       "network (docs/depth_network.md); the synthetic stand-in only works in "
                       "the simulator")
    load_key(config.mavlink)  # a key that cannot be used stops here, not after the network
    config = start_from_learned(config)
    summary = asyncio.run(_fly(config, waypoints, record, live))
    keep_learned(config, summary)
    return summary


async def _fly(config, waypoints, record: bool, live: str | None) -> dict:
    clock = MonotonicClock()
    notifier = SystemdNotifier()
    # before the network and the camera open: a recording that cannot be made stops here
    recording = open_recording(config.recorder, clock=clock, to_file=record, live=live,
                               metadata=recording_metadata(config))
    try:
        return await _fly_recorded(config, waypoints, clock, notifier, recording)
    finally:
        if recording is not None:
            recording.close()  # a no-op after a flight; else the file of a start that failed


async def _fly_recorded(config, waypoints, clock, notifier, recording) -> dict:
    network = await extending_start_timeout(notifier, lambda: DepthNetwork.open(
        config.depth_network, (config.camera.height, config.camera.width)))
    log.info("depth network on %s", network.provider)
    async with open_camera(config, clock) as driver:
        camera = CalibratedCamera(driver, resolve(config.camera,
                                                  getattr(driver, "camera_model", None)),
                                  grid_stamps(config.camera))
        autopilot = Autopilot.open(config.mavlink, clock)
        try:
            app = build_app(config, waypoints, autopilot=autopilot, camera=camera,
                            network=network, clock=clock, notifier=notifier)
            _stop_on_signals(app)
            return await recorded(app, recording)
        finally:
            notifier.stopping("mission ended")
            autopilot.close()


async def extending_start_timeout(notifier: SystemdNotifier, work, *, step_s: float = 10.0):
    """``work()`` run in a thread while asking systemd, every ``step_s``, for more start-up
    time: opening the network may build a TensorRT engine for minutes the first time, far
    beyond the unit's TimeoutStartSec. Each request covers three steps, so one late request
    does not get the service killed."""
    task = asyncio.ensure_future(asyncio.to_thread(work))
    while True:
        notifier.extend_timeout(3.0 * step_s)
        done, _ = await asyncio.wait({task}, timeout=step_s)
        if done:
            return task.result()


def build_app(config, waypoints, *, autopilot, camera: CalibratedCamera, network: DepthNetwork,
              clock, notifier=None) -> FlightApp:
    """The application on the real vehicle: the ONNX ``network`` on each rectified frame's RGB
    image, rescaled as ``[rescale]`` and ``[depth]`` say; worker threads; ``[go]`` waits for
    the operator."""
    depth = NetworkDepth(lambda frame: network(frame.image, channels="rgb"), config.rescale,
                         config.depth)
    calibration = camera.calibration
    return FlightApp.from_config(config, autopilot=autopilot, camera=camera,
                                 pinhole=calibration.rectified, T_B_C=calibration.T_B_C,
                                 depth=depth, waypoints_L=waypoints, clock=clock,
                                 lockstep=False, notifier=notifier)


def _stop_on_signals(app: FlightApp) -> None:
    loop = asyncio.get_running_loop()
    for number in (signal.SIGTERM, signal.SIGINT):
        name = signal.Signals(number).name
        loop.add_signal_handler(number, app.stop_requested, f"stop requested ({name})")

