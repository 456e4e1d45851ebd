"""``companion fly``: the application on the real vehicle.

The same :class:`~companion.flight.app.FlightApp` the simulator flies, wired to real devices: the
flight controller over ``[mavlink] url`` (serial on the Orin's UART, or UDP), the V4L2 camera of
``[v4l2]``, the user's ONNX depth network of ``[depth_network]`` (required here: the synthetic
stand-in needs a simulator's ground truth), the wall clock and worker threads. The mission is
``[flight] waypoints`` (or ``--goal`` on the command line).

Run by systemd (``systemd/companion.launch.systemd``, Type=notify): ``READY=1`` once preflight has
passed, ``WATCHDOG=1`` from the event loop's monitor (a stalled loop stops the pings and systemd
restarts the service), ``STOPPING=1`` at the end; SIGTERM or SIGINT ask the mission to stop,
which in the air means stop, hold and land.
"""

from __future__ import annotations

import asyncio
import logging
import signal

from autonomy.depth.network import DepthNetwork
from companion.flight.app import FlightApp
from companion.flight.perception import NetworkDepth
from companion.launch.systemd import SystemdNotifier
from drivers.camera.v4l2 import V4l2Camera
from drivers.clock import MonotonicClock
from drivers.mavlink.autopilot import Autopilot

log = logging.getLogger(__name__)


class FlyError(RuntimeError):
    """The real flight cannot start; the message says what to fix."""


def run(config, waypoints) -> dict:
    """Fly ``waypoints`` ((x, y, z) tuples in PX4's local frame, ENU) and return the summary."""
    if not waypoints:
        raise FlyError("no mission: set [flight] waypoints in the config or give --goal X,Y,Z")
    if not config.depth_network.model:
        raise FlyError("[depth_network] model is empty: companion fly needs the ONNX depth "
                       "network (docs/depth_network.md); the synthetic stand-in only works in "
                       "the simulator")
    return asyncio.run(_fly(config, waypoints))


async def _fly(config, waypoints) -> dict:
    clock = MonotonicClock()
    notifier = SystemdNotifier()
    network = DepthNetwork.open(config.depth_network, (config.camera.height,
                                                        config.camera.width))
    log.info("depth network on %s", network.provider)
    async with V4l2Camera(config.camera, config.v4l2, clock) as camera:
        autopilot = Autopilot.open(config.mavlink, clock)
        try:
            app = build_app(config, waypoints, autopilot=autopilot, camera=camera,
                            network=network, clock=clock, notifier=notifier)
            _stop_on_signals(app)
            return await app.run()
        finally:
            notifier.stopping("mission ended")
            autopilot.close()


def build_app(config, waypoints, *, autopilot, camera, network: DepthNetwork, clock,
              notifier=None) -> FlightApp:
    """The application on the real vehicle: the ONNX ``network`` on each frame's RGB image,
    rescaled as ``[rescale]`` and ``[depth]`` say; worker threads."""
    depth = NetworkDepth(lambda frame: network(frame.image, channels="rgb"), config.rescale,
                         config.depth)
    return FlightApp.from_config(config, autopilot=autopilot, camera=camera, depth=depth,
                                 T_B_C=config.camera.T_B_C(), waypoints_L=waypoints,
                                 clock=clock, lockstep=False, notifier=notifier)


def _stop_on_signals(app: FlightApp) -> None:
    loop = asyncio.get_running_loop()
    for number in (signal.SIGTERM, signal.SIGINT):
        name = signal.Signals(number).name
        loop.add_signal_handler(number, app.stop_requested, f"stop requested ({name})")

