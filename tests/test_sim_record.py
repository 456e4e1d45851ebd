"""A recorded dataset is self-consistent: its IMU integrates onto its ground truth, its depth
lies on the world's surfaces, and the same seed records the same flight."""

import hashlib
from dataclasses import replace

import numpy as np
import pytest

from autonomy.geometry import GRAVITY, make_pose, quat_to_rot, so3_exp
from companion.cli import main
from drivers.camera.options import CameraOptions
from drivers.dataset.euroc import read_camera, read_depth_png, read_groundtruth, read_imu
from drivers.sim.imu import ImuOptions
from drivers.sim.options import SimOptions
from drivers.sim.imu import ImuModel, flight_generators
from drivers.sim.record import (ACCELERATION_WINDOW_S, PATH_CLEARANCE, STATIC_SECONDS,
                                FlownMotion, RecordError,
                                TimedFollower, record_dataset, route_along, route_path,
                                smooth_path)
from autonomy.planning.height_wave import HeightWave
from autonomy.planning.speed_wave import SpeedWave
from drivers.sim.render import RenderError, Renderer
from drivers.sim.quadrotor import VehicleOptions
from drivers.sim.world import build_world

DURATION = 9.0  # 2 s on the ground, a climb, and the start of the path


def _egl_available() -> bool:
    try:
        Renderer(build_world("dome", 0), CameraOptions(width=16, height=16).pinhole()).close()
    except RenderError:
        return False
    return True


pytestmark = pytest.mark.skipif(not _egl_available(), reason="EGL/OpenGL unavailable here")


@pytest.fixture(scope="module")
def noiseless(tmp_path_factory):
    out = tmp_path_factory.mktemp("noiseless")
    sim = SimOptions(world="mine", seed=3)
    record_dataset(out, sim, CameraOptions(), VehicleOptions(), ImuOptions(enabled=False),
                   duration=DURATION)
    return out, sim


def test_layout_holds_every_stream_at_its_rate(noiseless):
    out, _ = noiseless
    imu, truth = read_imu(out), read_groundtruth(out)
    cam, depth = read_camera(out, "cam0"), read_camera(out, "depth0")
    assert len(imu.t_ns) == len(truth.t_ns) == DURATION * 200 + 1
    assert np.all(np.diff(imu.t_ns) == 5_000_000)
    assert len(cam.t_ns) == DURATION * 20 + 1
    assert np.array_equal(cam.t_ns, depth.t_ns)
    assert all(path.is_file() for path in cam.paths + depth.paths)
    expected = CameraOptions().pinhole()
    assert (cam.camera.width, cam.camera.height) == (expected.width, expected.height)
    assert [cam.camera.fx, cam.camera.cx, cam.camera.cy] == pytest.approx(
        [expected.fx, expected.cx, expected.cy], rel=1e-11)
    assert cam.rate_hz == 20.0
    # The flight leaves the ground: at least a metre of height is reached.
    assert truth.position[:, 2].max() > 1.0


def _integrate(imu, truth, first: int, samples: int):
    """Strapdown integration of body-frame IMU samples from the true state at ``first``."""
    R = quat_to_rot(truth.q_W_B[first])
    v, p = truth.velocity[first].copy(), truth.position[first].copy()
    gravity = np.array([0.0, 0.0, -GRAVITY])
    for k in range(first, first + samples):
        dt = (imu.t_ns[k + 1] - imu.t_ns[k]) * 1e-9
        a = R @ imu.accel[k] + gravity
        p += v * dt + 0.5 * a * dt * dt
        v += a * dt
        R = R @ so3_exp(imu.gyro[k] * dt)
    return p


@pytest.mark.parametrize("start_s", [0.5, 3.0, 5.5, 7.5])
def test_noiseless_imu_integrates_onto_ground_truth_for_a_second(noiseless, start_s):
    out, _ = noiseless
    imu, truth = read_imu(out), read_groundtruth(out)
    first = int(start_s * 200)
    end = _integrate(imu, truth, first, 200)
    assert np.linalg.norm(end - truth.position[first + 200]) < 0.05


def test_depth_images_lie_on_the_worlds_surfaces(noiseless):
    out, sim = noiseless
    world = build_world(sim.world, sim.seed)
    truth, depth_stream = read_groundtruth(out), read_camera(out, "depth0")
    rays = depth_stream.camera.rays()
    for index in (40, 120, 170):
        depth = read_depth_png(depth_stream.paths[index])
        row = np.searchsorted(truth.t_ns, depth_stream.t_ns[index])
        assert truth.t_ns[row] == depth_stream.t_ns[index]
        T_W_C = make_pose(quat_to_rot(truth.q_W_B[row]), truth.position[row]) @ depth_stream.T_B_C
        valid = np.isfinite(depth)
        assert valid.mean() > 0.99  # a mine has no sky
        points_C = (depth[..., None] * rays)[valid][::97]
        points_W = points_C @ T_W_C[:3, :3].T + T_W_C[:3, 3]
        on_floor = points_W[:, 2] < 0.02
        # Floor points sit on z = 0; every other point is on a wall, ceiling or pillar.
        assert np.all(np.abs(points_W[on_floor, 2]) < 0.02)
        assert np.all(world.obstacle_clearance(points_W[~on_floor]) < 0.02)


def test_the_same_seed_records_the_same_flight(tmp_path):
    digests = []
    for name, seed in (("a", 5), ("b", 5), ("c", 6)):
        record_dataset(tmp_path / name, SimOptions(world="dome", seed=seed), CameraOptions(),
                       VehicleOptions(), ImuOptions(), duration=0.5)
        files = ["imu0/data.csv", "state_groundtruth_estimate0/data.csv", "cam0/data/0.png"]
        digests.append([hashlib.sha256((tmp_path / name / "mav0" / f).read_bytes()).hexdigest()
                        for f in files])
    assert digests[0] == digests[1]
    assert digests[0][0] != digests[2][0]  # another seed: other noise (and another world)


def test_a_vehicle_seed_equal_to_the_seed_records_the_same_realistic_flight(tmp_path):
    """[sim] vehicle_seed flies another seed's vehicle; by default (-1), and set to the seed,
    the recording is the one it always was."""
    assert SimOptions().vehicle_for(5) == 5 and SimOptions(vehicle_seed=2).vehicle_for(5) == 2
    digests = []
    for name, vehicle_seed in (("a", -1), ("b", 5)):
        record_dataset(tmp_path / name, SimOptions(world="dome", seed=5, profile="realistic",
                                                   vehicle_seed=vehicle_seed),
                       CameraOptions(), VehicleOptions(), ImuOptions(), duration=0.5)
        files = ["imu0/data.csv", "cam0/data.csv"]
        digests.append([hashlib.sha256((tmp_path / name / "mav0" / f).read_bytes()).hexdigest()
                        for f in files])
    assert digests[0] == digests[1]


def test_a_noise_seed_flies_the_same_flight_with_other_sensor_noise(tmp_path):
    """[sim] noise_seed draws the sensors' noise alone: the world, route, vehicle and so the
    true motion stay the seed's, the IMU samples and the images change; set to the seed, the
    recording is the one it always was."""
    assert SimOptions().noise_for(5) == 5 and SimOptions(noise_seed=2).noise_for(5) == 2
    digests, motions = {}, {}
    for name, noise_seed in (("a", -1), ("b", 5), ("c", 6)):
        record_dataset(tmp_path / name, SimOptions(world="dome", seed=5, profile="realistic",
                                                   noise_seed=noise_seed),
                       CameraOptions(), VehicleOptions(), ImuOptions(), duration=0.5)
        mav = tmp_path / name / "mav0"
        files = [mav / "imu0/data.csv", min((mav / "cam0/data").glob("*.png"))]  # first frame
        digests[name] = [hashlib.sha256(f.read_bytes()).hexdigest() for f in files]
        # Time, position, attitude and velocity; the columns after them are the IMU's biases.
        motions[name] = np.loadtxt(mav / "state_groundtruth_estimate0/data.csv",
                                   delimiter=",")[:, :11]
    assert digests["a"] == digests["b"]
    assert all(a != c for a, c in zip(digests["a"], digests["c"]))
    assert np.array_equal(motions["a"], motions["c"])


def test_recording_refuses_a_folder_in_use_and_a_bad_duration(tmp_path):
    (tmp_path / "keep.txt").write_text("mine")
    with pytest.raises(RecordError, match="not empty"):
        record_dataset(tmp_path, SimOptions(), CameraOptions(), VehicleOptions(), ImuOptions(),
                       duration=1.0)
    with pytest.raises(RecordError, match="positive"):
        record_dataset(tmp_path / "new", SimOptions(), CameraOptions(), VehicleOptions(),
                       ImuOptions(), duration=float("nan"))


@pytest.mark.parametrize("speed", [0.0, -1.0, float("nan"), 12.5])
def test_recording_refuses_a_speed_the_vehicle_cannot_fly(tmp_path, speed):
    with pytest.raises(RecordError, match="xy_vel_max \\(12 m/s\\)"):
        record_dataset(tmp_path / "new", SimOptions(), CameraOptions(), VehicleOptions(),
                       ImuOptions(), duration=1.0, speed=speed)
    assert not (tmp_path / "new").exists()


def test_recording_refuses_a_speed_wave_that_would_fly_faster_than_the_vehicle(tmp_path):
    with pytest.raises(RecordError, match="half the speed wave's swing"):
        record_dataset(tmp_path / "new", SimOptions(), CameraOptions(), VehicleOptions(),
                       ImuOptions(), duration=1.0, speed=11.8, wave=SpeedWave(0.6, 3.3))


def test_record_command_cruises_at_the_speed_asked(tmp_path):
    """The planner's flights cruise at up to 2 m/s; ``--speed`` records at theirs."""
    small = ["--set", "camera.width=160", "--set", "camera.height=120"]
    cruise = {}
    for speed in (None, "1.8"):
        out = tmp_path / f"speed-{speed}"
        asked = [] if speed is None else ["--speed", speed]
        assert main(["sim", "record", "--world", "dome", "--seed", "1", "--duration", "12",
                     "--out", str(out), *asked, *small]) == 0
        velocity = np.diff(read_groundtruth(out).position[-600:], axis=0) * 200.0  # last 3 s
        cruise[speed] = np.median(np.hypot(velocity[:, 0], velocity[:, 1]))
    assert cruise[None] == pytest.approx(1.0, abs=0.05)
    assert cruise["1.8"] == pytest.approx(1.8, abs=0.1)


def test_record_command_swings_the_cruise_height_as_the_planners_height_wave(tmp_path):
    """``[planner] height_swing`` flies the recording as it flies the application: the cruise
    8 cm up and down every 2 s, its horizontal path the level recording's."""
    small = ["--set", "camera.width=160", "--set", "camera.height=120"]
    heights = {}
    for swing in ("0", "0.08"):
        out = tmp_path / f"swing-{swing}"
        assert main(["sim", "record", "--world", "dome", "--seed", "1", "--duration", "12",
                     "--out", str(out), "--set", f"planner.height_swing={swing}", *small]) == 0
        heights[swing] = read_groundtruth(out).position[-800:]  # the last 4 s, two periods
    level, waved = heights["0"], heights["0.08"]
    assert np.ptp(level[:, 2]) < 0.02
    assert np.ptp(waved[:, 2]) == pytest.approx(0.16, abs=0.03)
    np.testing.assert_allclose(waved[:, :2], level[:, :2], atol=0.05)


def test_record_command_writes_a_dataset_and_reports_it(tmp_path, capsys):
    out = tmp_path / "set"
    status = main(["sim", "record", "--world", "sewer", "--seed", "2", "--duration", "0.5",
                   "--out", str(out), "--set", "camera.width=320", "--set", "camera.height=240"])
    assert status == 0
    assert "recorded 0.5 s of sewer" in capsys.readouterr().out
    assert read_camera(out).camera.width == 320
    assert main(["sim", "record", "--duration", "0.5", "--out", str(out)]) == 1
    assert "not empty" in capsys.readouterr().err


def test_rounding_keeps_a_corner_whose_cut_would_touch_the_wall():
    """A path that turns tight round the corner of a block (0.7 m from it): plain corner
    cutting passes over the block, the guarded one keeps its clearance."""
    def clearance(xy):  # the solid block is x < 0, y < 0; free space elsewhere
        outside = np.maximum(xy, 0.0)
        return np.where((xy[:, 0] < 0) & (xy[:, 1] < 0), 0.0, np.hypot(*outside.T))

    polyline = np.array([[0.5, -10.0], [0.5, 0.5], [-10.0, 0.5]])  # north, then west
    plain = smooth_path(polyline)
    guarded = smooth_path(polyline, clearance=clearance, least=PATH_CLEARANCE)
    assert clearance(plain).min() < PATH_CLEARANCE
    assert clearance(guarded).min() >= PATH_CLEARANCE
    np.testing.assert_allclose(guarded[[0, -1]], polyline[[0, -1]])
    turn = np.abs(np.diff(np.unwrap(np.arctan2(*np.diff(guarded, axis=0).T[::-1]))))
    assert turn.max() < np.radians(45)  # still rounded, not the polyline's right angle


@pytest.mark.parametrize("world_name", ["mine", "sewer", "dome"])
def test_every_seeds_recorded_path_keeps_clear_of_the_walls(world_name):
    """Seeds 0-9 (mine 3 and sewer 1 and 8 once cut a corner into a wall, 0.08-0.22 m)."""
    for seed in range(10):
        world = build_world(world_name, seed)
        path = route_path(world, world.routes[seed % len(world.routes)])
        at_height = np.column_stack([path, np.full(len(path), world.cruise_height)])
        assert world.obstacle_clearance(at_height).min() >= PATH_CLEARANCE, seed


def test_the_vins_runs_on_a_noiseless_recording_without_a_rebuild(noiseless):
    """A recording of the exact IMU says its noise is nil (sensor.yaml): the VINS weighs it at
    its density floors, which must still leave every window well posed (``eval vio`` of such
    a recording once rebuilt the smoother at nearly every keyframe; on this 9 s one it made a
    single keyframe)."""
    from autonomy.vins.options import VinsOptions
    from companion.tools.eval.vio import read_vio_dataset, run_vins

    out, _ = noiseless
    data = read_vio_dataset(out)
    assert data.noise.gyro_random_walk == 0.0 and data.noise.accel_noise_density == 0.0
    trace = run_vins(data, VinsOptions(gyro_noise_scale=10.0), consistency=False)
    assert trace.static_init is not None and sum(trace.keyframe) > 10
    assert trace.resets == 0


def test_a_flights_path_is_followed_from_its_start_at_the_height_it_flew():
    """A flight standing at the start, climbing to 1.6 m, hovering and turning there (the same
    point again and again), then flying the dome seed 0 route's own path: the route starts on
    the floor where the flight did, at the height it flew, and the path is the flight's,
    smoothed, with the route's clearance."""
    world = build_world("dome", 0)
    flown = route_path(world, world.routes[0])
    ground = [[*flown[0], 0.0]] * 20
    climb = [[*flown[0], z] for z in np.linspace(0.1, 1.6, 16)]
    hover = [[*flown[0], 1.6]] * 30
    positions = np.array(ground + climb + hover + [[*xy, 1.6] for xy in flown])
    route, path = route_along(world, positions)
    np.testing.assert_allclose(route.start, [*flown[0], 0.0])
    assert route.cruise_height == pytest.approx(1.6)
    np.testing.assert_allclose(path[[0, -1]], flown[[0, -1]], atol=0.01)
    nearest = np.min(np.linalg.norm(path[:, None, :] - flown[None, ::5, :], axis=2), axis=1)
    assert nearest.max() < 0.5
    at_height = np.column_stack([path, np.full(len(path), 1.6)])
    assert world.obstacle_clearance(at_height).min() >= PATH_CLEARANCE


def test_a_flight_that_never_flew_has_no_path_to_follow():
    world = build_world("dome", 0)
    on_the_ground = np.zeros((50, 3))
    with pytest.raises(RecordError, match="never flew"):
        route_along(world, on_the_ground)
    hovering = np.array([[0.0, 0.0, 1.5]] * 50)
    with pytest.raises(RecordError, match="never moved"):
        route_along(world, hovering)


def _flight_with_a_stop_and_a_turn() -> FlownMotion:
    """2 s on the floor, a climb to 1.5 m at 1 m/s, 4 s east at 2 m/s, 2 s stopped turning
    90 degrees left at 45 deg/s, 2 s north at 1 m/s, a landing at 1 m/s and 1 s on the
    floor: 20 samples a second, stamped from 100 s."""
    t = np.arange(0.0, 14.0, 0.05)
    x = np.clip(t - 3.5, 0.0, 4.0) * 2.0
    y = np.clip(t - 9.5, 0.0, 2.0)
    z = np.interp(t, [0.0, 2.0, 3.5, 11.5, 13.0], [0.0, 0.0, 1.5, 1.5, 0.0])
    yaw = np.radians(np.clip(t - 7.5, 0.0, 2.0) * 45.0)
    return FlownMotion("dome", 0, "ideal", times=t + 100.0,
                       positions=np.column_stack([x, y, z]), yaws=yaw)


def test_a_timed_follower_flies_the_flights_motion_from_its_lift_off():
    """The flight's climb, speeds, stop and turn in place come back at the same times after
    it lifted off, with their rates as feed-forward; after its last airborne point, a hover
    there."""
    flown = _flight_with_a_stop_and_a_turn()
    follower = TimedFollower(flown)
    assert follower.takes_off
    assert follower.standing_s == pytest.approx(2.0)  # as long as the flight stood
    late = TimedFollower(replace(flown, times=flown.times[30:], positions=flown.positions[30:],
                                 yaws=flown.yaws[30:]))
    assert late.standing_s == STATIC_SECONDS  # its first 0.5 s on the floor is too short
    descending = np.column_stack([flown.positions[:, :2],
                                  np.linspace(1.5, 0.5, len(flown.times))])
    in_the_air = TimedFollower(replace(flown, positions=descending))  # recorded once airborne
    assert in_the_air.span == pytest.approx(flown.times[-1] - flown.times[0])
    # from its last sample on the floor, 2.0 s, to its last over 0.3 m, 12.65 s
    assert follower.span == pytest.approx(10.65)
    assert follower.length == pytest.approx(10.0)
    assert follower.start_yaw == 0.0
    on_the_floor = follower.target(0.0)
    np.testing.assert_allclose(on_the_floor.position, 0.0, atol=1e-12)
    climbing = follower.target(1.0)
    np.testing.assert_allclose(climbing.position, [0.0, 0.0, 1.0])
    np.testing.assert_allclose(climbing.velocity, [0.0, 0.0, 1.0], atol=1e-9)
    np.testing.assert_allclose(climbing.acceleration, 0.0, atol=1e-9)
    cruising = follower.target(3.5)
    np.testing.assert_allclose(cruising.position, [4.0, 0.0, 1.5])
    np.testing.assert_allclose(cruising.velocity, [2.0, 0.0, 0.0], atol=1e-9)
    # the stop, within one sample: its 2 m/s lost in 0.05 s is fed forward averaged over 0.2 s
    braking = follower.target(5.5)
    assert braking.acceleration[0] == pytest.approx(-2.0 / ACCELERATION_WINDOW_S, rel=0.1)
    turning = follower.target(6.5)
    np.testing.assert_allclose(turning.position, [8.0, 0.0, 1.5])
    np.testing.assert_allclose(turning.velocity, 0.0, atol=1e-9)
    assert turning.yaw == pytest.approx(np.radians(45.0))
    assert turning.yaw_rate == pytest.approx(np.radians(45.0))
    north = follower.target(8.5)
    np.testing.assert_allclose(north.position, [8.0, 1.0, 1.5])
    np.testing.assert_allclose(north.velocity, [0.0, 1.0, 0.0], atol=1e-9)
    assert north.yaw == pytest.approx(np.radians(90.0))
    after = follower.target(30.0)
    np.testing.assert_allclose(after.position, [8.0, 2.0, 0.35], atol=1e-9)
    np.testing.assert_allclose(after.velocity, 0.0)
    assert after.yaw_rate == 0.0


def test_a_timed_follower_turns_the_short_way_through_plus_minus_180_degrees():
    """A flight turning left through 180 degrees: its yaws wrap from +179 to -179, which the
    follower must not take for a turn back of 358 degrees."""
    flown = _flight_with_a_stop_and_a_turn()
    wrapped = np.angle(np.exp(1j * (flown.yaws + np.radians(135.0))))
    follower = TimedFollower(replace(flown, yaws=wrapped))
    assert np.all(np.abs(follower.yaw_rates) <= np.radians(45.0) + 1e-9)
    assert follower.target(8.5).yaw - follower.target(0.0).yaw == pytest.approx(np.radians(90))


def test_a_timed_follower_refuses_a_flight_it_cannot_fly_again():
    flown = _flight_with_a_stop_and_a_turn()
    with pytest.raises(RecordError, match="never flew"):
        TimedFollower(replace(flown, positions=np.zeros_like(flown.positions)))
    with pytest.raises(RecordError, match="one time, position and yaw"):
        TimedFollower(replace(flown, times=flown.times[:-1]))
    with pytest.raises(RecordError, match="must increase"):
        TimedFollower(replace(flown, times=np.full_like(flown.times, 100.0)))


def test_a_recording_along_a_flight_draws_the_flights_imu(tmp_path):
    """Seed 3's recording along a flight of seed 3 reads gravity through the scale and
    misalignment matrix the flight's IMU had (``SimulatedVehicle``'s draw), not through the
    one the recorder's own route of seed 3 draws: standing still with every other error off,
    the mean specific force is that matrix times g."""
    imu = ImuOptions(gyro_noise_density=0.0, accel_noise_density=0.0, gyro_bias_random_walk=0.0,
                     accel_bias_random_walk=0.0, accel_vibration_amplitude=0.0,
                     gyro_vibration_amplitude=0.0, gyro_turn_on_bias=0.0,
                     accel_turn_on_bias=0.0, gyro_warmup_drift=0.0, accel_warmup_drift=0.0)
    flight = replace(_flight_with_a_stop_and_a_turn(), seed=3)  # the world and seed it flew
    record_dataset(tmp_path / "along", SimOptions(profile="realistic"),
                   CameraOptions(width=32, height=24), VehicleOptions(), imu, duration=1.0,
                   along=flight, timed=True)
    read = read_imu(tmp_path / "along").accel.mean(axis=0)
    gravity = np.array([0.0, 0.0, 9.80665])
    flights = ImuModel(imu, *flight_generators(3, 3))._accel_matrix @ gravity
    recorders = ImuModel(imu, np.random.default_rng([3, 1]),
                         np.random.default_rng([3, 1]))._accel_matrix @ gravity
    np.testing.assert_allclose(read, flights, atol=1e-4)
    assert np.abs(read - recorders).max() > 1e-3


@pytest.mark.parametrize("wave", [{"wave": SpeedWave(0.6, 3.3)},
                                  {"height_wave": HeightWave(0.08, 2.0)}])
def test_recording_refuses_a_timed_flight_without_a_flight_or_with_a_wave(tmp_path, wave):
    with pytest.raises(RecordError, match="needs the flight"):
        record_dataset(tmp_path / "new", SimOptions(), CameraOptions(), VehicleOptions(),
                       ImuOptions(), duration=None, timed=True)
    with pytest.raises(RecordError, match="no speed or height wave"):
        record_dataset(tmp_path / "new", SimOptions(), CameraOptions(), VehicleOptions(),
                       ImuOptions(), duration=None, timed=True,
                       along=_flight_with_a_stop_and_a_turn(), **wave)
    with pytest.raises(RecordError, match="positive"):
        record_dataset(tmp_path / "new", SimOptions(), CameraOptions(), VehicleOptions(),
                       ImuOptions(), duration=None)


def test_record_along_refuses_another_world_or_seed_and_a_missing_flight(tmp_path, capsys):
    assert main(["sim", "record", "--along", str(tmp_path / "flight.mcap"), "--seed", "3",
                 "--out", str(tmp_path / "out")]) == 1
    assert "drop --world and --seed" in capsys.readouterr().err
    assert main(["sim", "record", "--along", str(tmp_path / "flight.mcap"),
                 "--out", str(tmp_path / "out")]) == 1
    assert "no such file" in capsys.readouterr().err
    assert main(["sim", "record", "--timed", "--out", str(tmp_path / "out")]) == 1
    assert "give it --along" in capsys.readouterr().err
    assert main(["sim", "record", "--along", str(tmp_path / "flight.mcap"), "--timed",
                 "--speed", "2", "--out", str(tmp_path / "out")]) == 1
    assert "drop --speed" in capsys.readouterr().err
