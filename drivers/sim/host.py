"""The simulator host: the simulated vehicle served for one flight, beside the application.

What ``companion sim fly`` and ``companion eval nav`` fly against (docs/simulator.md): the
mock PX4 on loopback UDP or, for a serial link, on a pseudo-terminal
(:func:`drivers.sim.serve.serve`), the rendered camera, the network
the application runs (the user's ONNX model on the image, or the synthetic stand-in on the
rendered depth) or the true depth, injected faults, and the true path for scoring.

Clocks: :class:`LockstepSimulator` runs on the application's loop and one
:class:`~drivers.clock.SimClock` (deterministic, as fast as the CPU allows);
:class:`ThreadedSimulator` runs in its own thread on the wall clock, its frames crossing to the
application's loop through a :class:`FrameSlot`, as a real camera's would.

Ground truth stays here and is used only for scoring: the flown path, its clearance from the
obstacles, collisions, the distance to the goal at the end.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import resource
import signal
import socket
import threading
import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np

from autonomy.depth.network import DepthNetwork
from autonomy.depth.synthetic import SyntheticNetwork
from autonomy.messages import DepthDiagnostics, Frame, MetricDepth
from autonomy.geometry import so3_log
from autonomy.trajectory import split_displacement
from drivers.camera.calibration import CameraCalibration
from drivers.clock import MonotonicClock, SimClock
from drivers.mavlink import px4_protocol
from drivers.sim.camera import CameraHead, SimCamera
from drivers.sim.faults import Fault, FaultSchedule
from drivers.sim.imu import ImuModel, flight_generators
from drivers.sim.options import WORLD_NAMES
from drivers.sim.render import Renderer
from drivers.sim.serve import SERIAL_BAUD, serve
from drivers.sim.world import ROBOT_RADIUS, World

log = logging.getLogger(__name__)

#: How often the simulator side samples the true path for the summary, Hz.
TRACK_RATE_HZ = 20.0
#: Simulated seconds between progress lines.
PROGRESS_PERIOD_S = 2.0
#: The true height at or below which the vehicle is on the floor (it rests at z = 0), metres.
FLOOR_CONTACT_M = 0.05
#: Longest event-loop stall a ``loop_stall`` fault injects, seconds.
MAX_STALL_S = 5.0
#: Longest wait for the simulator thread to come up, seconds.
SIM_START_TIMEOUT_S = 30.0


class SimError(RuntimeError):
    """The simulated flight could not be set up; the message says why."""


#: Where the planner's depth comes from: the estimate (network and rescaler on the VINS map)
#: or the renderer's true depth (the evaluation's baseline, as the paper's ground-truth runs).
DEPTH_SOURCES = ("estimated", "truth")


@dataclass(frozen=True)
class SimMission:
    """What to fly: ``world`` from ``seed``; route ``pair`` or a ``goal`` (x, y, z) from the
    pair's start, through the waypoints ``via`` first (each x, y, z; in order); ``depth`` one
    of :data:`DEPTH_SOURCES`; ``tracks`` one of :data:`drivers.sim.truth_tracks.TRACK_SOURCES`;
    ``start_yaw_deg`` the heading the vehicle stands at on the ground (degrees
    counter-clockwise from east; default: facing the first leg); ``link`` one of
    :data:`drivers.sim.serve.LINKS`; ``go_after_s``: the operator's go comes that many
    simulated seconds after the mission starts waiting for it (None: the command line gave
    it)."""

    world: str = "dome"
    seed: int = 0
    pair: int = 0
    goal: tuple[float, float, float] | None = None
    via: tuple[tuple[float, float, float], ...] = ()
    faults: tuple[Fault, ...] = ()
    clock: str = "lockstep"
    depth: str = "estimated"
    tracks: str = "tracker"
    start_yaw_deg: float | None = None
    link: str = "udp"
    go_after_s: float | None = None


def mission_waypoints(world: World, mission: SimMission, height: float
                      ) -> tuple[np.ndarray, np.ndarray, float]:
    """``(start, waypoints (N, 3), start_yaw)`` of the mission: the route's start, the corners
    of its collision-free path at ``height`` ending at its goal (or the mission's ``via``
    waypoints and its ``goal``), and the heading it stands at (the first leg's unless the
    mission gives one)."""
    if not 0 <= mission.pair < len(world.routes):
        raise SimError(f"{world.name} has start/goal pairs 0..{len(world.routes) - 1}, "
                       f"not {mission.pair}")
    route = world.routes[mission.pair]
    start = np.asarray(route.start, dtype=float)
    if mission.via and mission.goal is None:
        raise SimError("waypoints to fly through (via) need a goal to fly to after them")
    if mission.goal is not None:
        waypoints = np.array([_point(f"via waypoint {k + 1}", point)
                              for k, point in enumerate(mission.via)]
                             + [_point("goal", mission.goal)])
    else:
        corners = world.find_path(start[:2], route.goal[:2], ROBOT_RADIUS)
        if corners is None:
            raise SimError(f"{world.name}: route {route.name} has no path with "
                           f"{ROBOT_RADIUS} m clearance")
        waypoints = np.column_stack([corners[1:], np.full(len(corners) - 1, height)])
        waypoints[-1] = route.goal
    first = waypoints[0, :2] - start[:2]
    if mission.start_yaw_deg is None:
        return start, waypoints, math.atan2(first[1], first[0])
    if not math.isfinite(mission.start_yaw_deg):
        raise SimError(f"start yaw must be a finite number of degrees, "
                       f"got {mission.start_yaw_deg}")
    return start, waypoints, math.radians(mission.start_yaw_deg)


def _point(name: str, point) -> np.ndarray:
    """``point`` as a (3,) array; SimError unless it is three finite numbers."""
    try:
        array = np.asarray(point, dtype=float)
    except (TypeError, ValueError):
        array = np.zeros(0)
    if array.shape != (3,) or not np.isfinite(array).all():
        raise SimError(f"{name} must be three finite numbers x,y,z, got {point}")
    return array


def goal_distance(position, goal) -> float:
    return float(np.linalg.norm(np.asarray(position) - np.asarray(goal)))


def free_udp_port() -> int:
    """A loopback UDP port nobody is bound to now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def simulated_network(config, seed: int, faults: FaultSchedule, sim_time: Callable[[], float]):
    """The network the application runs: the user's ONNX model on the image, else the
    synthetic stand-in on the rendered depth; NaN everywhere while a ``network_nan`` fault is
    on, one value everywhere (the frame's median, so of a plausible size) while a
    ``network_const`` fault is: what broken engines output."""
    if config.depth_network.model:
        model = DepthNetwork.open(config.depth_network,
                                  (config.camera.height, config.camera.width))
        infer = lambda frame: model(frame.image, channels="rgb")  # noqa: E731
    else:
        stand_in = SyntheticNetwork(config.synthetic_depth.for_profile(config.sim.profile),
                                    seed=seed)
        infer = lambda frame: stand_in(frame.truth_depth, frame.image)  # noqa: E731

    def source(frame):
        disparity = infer(frame)
        if faults.active("network_nan", sim_time()):
            return np.full_like(disparity, np.nan)
        if faults.active("network_const", sim_time()):
            return np.full_like(disparity, np.nanmedian(disparity))
        return disparity
    return source


class TruthDepth:
    """The renderer's true depth as the application's metric depth, fully confident (the
    evaluation's baseline, as the paper's ground-truth runs); NaN (nothing within the far
    plane) becomes ``max_range``, which the planner knows to be free beyond
    (:mod:`autonomy.planning.history`). A depth source of the application
    (:class:`companion.flight.perception.DepthSource`): no rescaling, so :meth:`metric` passes
    :meth:`infer`'s result through."""

    def __init__(self, max_range: float):
        self.max_range = max_range

    def infer(self, frame: Frame) -> MetricDepth:
        depth = np.nan_to_num(frame.truth_depth, nan=self.max_range).astype(np.float32)
        return MetricDepth(frame.t, depth, np.ones_like(depth), False,
                           DepthDiagnostics(0, 0, math.nan, "truth", 0.0))

    def metric(self, depth: MetricDepth, sparse_map) -> MetricDepth:
        return depth


class TruthTrack:
    """The true path, sampled on the simulator's side, for the summary."""

    def __init__(self):
        self.t: list[float] = []  # the application's clock at each sample
        self.positions: list[np.ndarray] = []
        self.armed: list[bool] = []
        self.px4_landing: list[bool] = []  # PX4 in Land: a touch-down is meant

    async def run(self, sim, clock, goal: np.ndarray, progress=None) -> None:
        """Sample until cancelled; every :data:`PROGRESS_PERIOD_S` a line to ``progress``."""
        next_line = 0.0
        while True:
            self.t.append(clock.now())
            self.positions.append(np.array(sim.vehicle.state.position))
            self.armed.append(sim.vehicle.armed)
            self.px4_landing.append(sim.px4.mode == px4_protocol.AUTO_LAND)
            if progress is not None and sim.time >= next_line:
                progress(self._progress_line(sim, goal))
                next_line = sim.time + PROGRESS_PERIOD_S
            await clock.sleep(1.0 / TRACK_RATE_HZ)

    def _at(self, t: float) -> np.ndarray:
        """The true position at the first sample not before ``t`` (the last one after)."""
        k = min(int(np.searchsorted(self.t, t)), len(self.positions) - 1)
        return self.positions[k]

    def path_length_between(self, t0: float, t1: float) -> float:
        """Metres flown in truth from ``t0`` to ``t1`` (application clock)."""
        t = np.asarray(self.t)
        path = np.array(self.positions).reshape(-1, 3)[(t >= t0) & (t <= t1)]
        return float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())

    def first_floor_contact(self, t0: float, t1: float) -> tuple[float, np.ndarray] | None:
        """The first sample from ``t0`` up to ``t1`` (application clock) with the vehicle on
        the floor (:data:`FLOOR_CONTACT_M`), armed and PX4 not landing it: flown there. Its
        time and true position; None if none. (Disarmed in the air, by a fault or PX4, it
        falls; PX4 lands it on a failsafe of its own, such as a lost offboard link.) Sampled
        at :data:`TRACK_RATE_HZ`: a touch shorter than a sample's 50 ms may be missed."""
        t = np.asarray(self.t)
        height = np.array(self.positions).reshape(-1, 3)[:, 2]
        flown = np.asarray(self.armed, dtype=bool) & ~np.asarray(self.px4_landing, dtype=bool)
        on_floor = np.flatnonzero((t >= t0) & (t < t1) & (height <= FLOOR_CONTACT_M) & flown)
        if len(on_floor) == 0:
            return None
        return self.t[on_floor[0]], self.positions[on_floor[0]]

    def _progress_line(self, sim, goal: np.ndarray) -> str:
        position = self.positions[-1]
        speed = float(np.linalg.norm(sim.vehicle.state.velocity))
        return (f"t={sim.time:6.1f} s  {sim.px4.mode.name:<11}  "
                f"{goal_distance(position, goal):6.1f} m to goal  {speed:4.1f} m/s  "
                f"height {position[2]:4.1f} m")

    def score(self, world: World, goal: np.ndarray, estimate: dict | None = None) -> dict:
        """The flight in truth: its start, length, least clearance, closest approach to
        ``goal`` and, given the application's ``estimate`` ``{"t", "position_L"}`` of where it
        was when navigation ended (local frame = world frame here), how far that lies from the
        truth at that time: the VINS's drift over the flight, and that error split over the
        path from the start (``position_error_split``: the path's scale and bearing, metres
        along, across and in height; ``autonomy.trajectory.split_displacement``, the VINS
        taken to have started where the vehicle did, where it was tied to the local frame)."""
        path = np.array(self.positions).reshape(-1, 3)
        if len(path) == 0:
            return {"start": None, "path_length_m": 0.0, "min_clearance_m": None,
                    "closest_to_goal_m": None, "position_error_m": None,
                    "position_error_split": None}
        airborne = path[path[:, 2] > 0.3]
        clearance = world.obstacle_clearance(airborne) if len(airborne) else np.array([np.inf])
        return {
            "start": [round(float(v), 3) for v in path[0]],
            "path_length_m": float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum()),
            "min_clearance_m": float(clearance.min()) if np.isfinite(clearance.min()) else None,
            "closest_to_goal_m": float(np.linalg.norm(path[:, :2] - goal[:2], axis=1).min()),
            **self._vins_error(path[0], estimate),
        }

    def _vins_error(self, start: np.ndarray, estimate: dict | None) -> dict:
        """``position_error_m`` and ``position_error_split`` (:meth:`score`), None without
        an ``estimate``."""
        if estimate is None:
            return {"position_error_m": None, "position_error_split": None}
        truth, believed = self._at(estimate["t"]), np.asarray(estimate["position_L"], float)
        split = split_displacement(start, truth, start, believed)
        return {"position_error_m": float(np.linalg.norm(believed - truth)),
                "position_error_split": None if split is None else asdict(split)}


def camera_head(config, world: str, seed: int) -> CameraHead:
    """The simulated camera ``config`` describes in ``world``: ideal, or in the realistic
    profile behind ``[sim_camera]``'s sensor, its errors drawn from ``seed`` (its noise from
    ``[sim] noise_seed``'s, its mounting from ``[sim] vehicle_seed``'s)."""
    camera = config.camera
    return CameraHead(camera.pinhole(), camera.rate_hz, camera.T_B_C(),
                      config.sim_camera.for_profile(config.sim.profile), world,
                      np.random.default_rng([config.sim.noise_for(seed), 3]),
                      np.random.default_rng([config.sim.vehicle_for(seed), 3]),
                      numbered=config.sim.camera_counter)


@dataclass(frozen=True)
class VehicleErrors:
    """What a simulated vehicle's calibration leaves wrong, as the simulator draws it:
    ``mount_rotation_deg``, the camera's true rotation off its configured mounting as a
    rotation vector in the body's axes (FLU; its z, the camera's yaw on the body, turns the
    path the VINS reckons: docs/vins.md, "The path's bearing is the camera mounting's yaw"),
    degrees; ``accel_scale_error``, each accelerometer axis's sensitivity error as PX4's
    calibration leaves it (FLU, fractions; its z sets the map's scale: docs/vins.md, "The
    accelerometer as PX4 calibrates it"). Zero in the ideal profile."""

    mount_rotation_deg: tuple[float, float, float]
    accel_scale_error: tuple[float, float, float]


def vehicle_errors(config, seed: int) -> VehicleErrors:
    """The calibration errors of the vehicle a simulated flight of ``seed`` flies in
    ``config`` (drawn from ``[sim] vehicle_seed``'s stream as the flight draws them)."""
    head = camera_head(config, WORLD_NAMES[0], seed)  # the world sets only the light
    R_configured, R_true = head.T_B_C_configured[:3, :3], head.T_B_C[:3, :3]
    mounting = np.degrees(so3_log(R_true @ R_configured.T))
    imu = ImuModel(config.imu.for_profile(config.sim.profile),
                   *flight_generators(config.sim.noise_for(seed), config.sim.vehicle_for(seed)))
    scale = np.diag(imu.accel_matrix) - 1.0
    return VehicleErrors(tuple(float(v) for v in mounting), tuple(float(v) for v in scale))


async def stall_when_due(faults: FaultSchedule, sim) -> None:
    """The ``loop_stall`` fault: block this event loop (a runaway computation) for the
    fault's duration, at most :data:`MAX_STALL_S`."""
    stall = next((f for f in faults.faults if f.kind == "loop_stall"), None)
    if stall is None:
        return
    while not faults.active("loop_stall", sim.time):
        await asyncio.sleep(0.01)
    log.warning("injecting an event-loop stall of %.1f s", min(stall.duration_s, MAX_STALL_S))
    time.sleep(min(stall.duration_s, MAX_STALL_S))


async def fill_disk_when_due(faults: FaultSchedule, sim, recording_path) -> tuple | None:
    """The ``disk_full`` fault: from its start, no file of this process may grow past the size
    the recording has then (``RLIMIT_FSIZE``; SIGXFSZ ignored, so a write fails with EFBIG
    rather than killing the process). Returns the limits to restore (:func:`empty_disk`),
    or None when the fault never started."""
    fault = next((f for f in faults.faults if f.kind == "disk_full"), None)
    if fault is None or recording_path is None:
        return None
    while not faults.active("disk_full", sim.time):
        await asyncio.sleep(0.01)
    size = os.path.getsize(recording_path)
    log.warning("injecting a full disk: no file grows past %d bytes", size)
    before = (resource.getrlimit(resource.RLIMIT_FSIZE),
              signal.signal(signal.SIGXFSZ, signal.SIG_IGN))
    resource.setrlimit(resource.RLIMIT_FSIZE, (size, before[0][1]))
    return before


def empty_disk(before) -> None:
    """Undo :func:`fill_disk_when_due` (``before``: what it returned)."""
    if before is not None:
        limits, handler = before
        resource.setrlimit(resource.RLIMIT_FSIZE, limits)
        signal.signal(signal.SIGXFSZ, handler)


class Simulator:
    """The simulator side of a flight: what it serves, and the true path it tracks."""

    def __init__(self, config, world, mission, start_pose, faults, goal, progress):
        # start_pose: (position, yaw) the vehicle stands at on the ground, the mission's
        self.config, self.world, self.mission = config, world, mission
        self.start_pose, self.faults, self.goal = start_pose, faults, goal
        self.progress = progress
        self.track = TruthTrack()
        self.port = free_udp_port() if mission.link == "udp" else None
        self.head = camera_head(config, world.name, mission.seed)

    def calibration(self) -> CameraCalibration:
        """The camera as the application knows it: the lens the simulated camera reports (its
        factory calibration), at the configured mounting and time offset; the true mounting
        and stamps may differ (the realistic profile)."""
        camera = self.config.camera
        return CameraCalibration(self.head.model, camera.pinhole(), camera.T_B_C(),
                                 camera.time_offset_s, "simulated camera")

    def companion_url(self) -> str:
        """Where the application reaches the mock PX4, once :meth:`start` has returned."""
        if self.port is None:
            return f"serial://{self.sim.px4.link.pty_path}:{SERIAL_BAUD}"
        return f"udpout://127.0.0.1:{self.port}"

    def _serve(self, clock_mode: str, stop, on_ready, sim_clock=None):
        c = self.config
        url = "pty" if self.port is None else f"udpin://127.0.0.1:{self.port}"
        return serve(url, self.world, seed=c.sim.noise_for(self.mission.seed),
                     vehicle_seed=c.sim.vehicle_for(self.mission.seed),
                     clock_mode=clock_mode, vehicle_options=c.vehicle,
                     imu_options=c.imu.for_profile(c.sim.profile),
                     baro_options=c.baro.for_profile(c.sim.profile),
                     px4_options=c.px4, stop=stop, sim_clock=sim_clock, on_ready=on_ready,
                     start=self.start_pose[0], start_yaw=self.start_pose[1], faults=self.faults)


class LockstepSimulator(Simulator):
    """The simulator on the application's loop and clock (a :class:`SimClock`)."""

    def __init__(self, *args):
        super().__init__(*args)
        self.clock = SimClock(0.0)
        self._stop = asyncio.Event()

    async def start(self):
        ready: asyncio.Future = asyncio.get_running_loop().create_future()
        self._server = asyncio.create_task(self._serve("lockstep", self._stop,
                                                       ready.set_result, self.clock))
        self.sim = await ready
        self._tracker = asyncio.create_task(self.track.run(self.sim, self.clock, self.goal,
                                                           self.progress))
        self._renderer = Renderer(self.world, self.head.render_camera)
        self._camera = SimCamera(self.sim, self._renderer, self.clock, self.head)
        return self.sim, self._camera, self.clock

    async def stop(self) -> None:
        self._stop.set()
        self._tracker.cancel()
        await self._camera.stop()
        await asyncio.gather(self._server, self._tracker, return_exceptions=True)
        self._renderer.close()


class ThreadedSimulator(Simulator):
    """The simulator in its own thread and event loop on the wall clock (real time): its
    physics, mock PX4 and camera keep going whatever the application's loop does. Frames
    cross to the application's loop through a newest-frame slot."""

    def __init__(self, *args):
        super().__init__(*args)
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._error: BaseException | None = None

    async def start(self):
        self.frames = FrameSlot(asyncio.get_running_loop())
        self._thread = threading.Thread(target=self._main, name="simulator", daemon=True)
        self._thread.start()
        if not await asyncio.to_thread(self._ready.wait, SIM_START_TIMEOUT_S):
            raise SimError("the simulator thread did not start")
        if self._error is not None:
            raise SimError(f"the simulator thread failed: {self._error}")
        return self.sim, self.frames, MonotonicClock()

    async def stop(self) -> None:
        self._stop.set()
        await asyncio.to_thread(self._thread.join, 10.0)

    def _main(self) -> None:
        try:
            asyncio.run(self._run())
        except BaseException as error:  # noqa: BLE001 - reported to the starting thread
            self._error = error
            self._ready.set()

    async def _run(self) -> None:
        clock = MonotonicClock()
        started: asyncio.Future = asyncio.get_running_loop().create_future()
        server = asyncio.create_task(self._serve("realtime", self._stop, started.set_result))
        self.sim = await started
        with Renderer(self.world, self.head.render_camera) as renderer:
            camera = SimCamera(self.sim, renderer, clock, self.head)
            tasks = [asyncio.create_task(self._pump(camera)), asyncio.create_task(
                self.track.run(self.sim, clock, self.goal, self.progress))]
            self._ready.set()
            await server
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await camera.stop()

    async def _pump(self, camera: SimCamera) -> None:
        while True:
            frame = await camera.next_frame()
            self.frames.put(frame, camera.lost)


class FrameSlot:
    """The newest frame, put from any thread, awaited on one event loop; frames nobody took
    before a newer one came are counted in ``dropped``, and ``lost`` is the camera's own count
    of the frames it never delivered (as a real driver's, :mod:`drivers.camera.base`)."""

    def __init__(self, loop: asyncio.AbstractEventLoop):
        self._loop = loop
        self._frame = None
        self._arrived = asyncio.Event()
        self.dropped = 0
        self.lost = 0

    def put(self, frame, lost: int) -> None:
        """Hand over ``frame``, with the camera's count of lost frames so far."""
        self._loop.call_soon_threadsafe(self._set, frame, lost)

    def _set(self, frame, lost: int) -> None:
        if self._frame is not None:
            self.dropped += 1
        self._frame, self.lost = frame, lost
        self._arrived.set()

    async def next_frame(self):
        await self._arrived.wait()
        self._arrived.clear()
        frame, self._frame = self._frame, None
        return frame
