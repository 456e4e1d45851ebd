"""The realistic camera sensor (drivers/sim/sensor.py): each effect does what the physics says.

Most tests feed the sensor a synthetic "render" (a known pattern at a known depth) so that the
expected image follows from the geometry alone; the last ones go through the real renderer,
the camera head and ``sim record``.
"""

import math

import cv2
import numpy as np
import pytest

from autonomy.geometry import PinholeCamera, distort_points, rot_to_quat, so3_log
from autonomy.options import OptionError
from drivers.dataset.euroc import read_camera, read_camera_truth, read_imu
from drivers.sim.camera import CameraHead
from drivers.sim.sensor import (REFERENCE_EXPOSURE_S, REFERENCE_LUX, CameraSensor,
                                SensorOptions, camera_twist)

CAMERA = PinholeCamera.from_hfov(160, 120, math.radians(90.0))
PERIOD = 0.05


def quiet(exposure_s: float, **changes) -> SensorOptions:
    """A sensor without noise, vignetting, lens or time effects, exposing exactly
    ``exposure_s`` at unity gain in a dome lit so that the image level equals the radiance."""
    base = dict(time_offset_ms=0.0, timestamp_jitter_ms=0.0, drop_probability=0.0,
                distortion=(), corner_illumination=1.0, full_well_electrons=1e12,
                read_noise_electrons=0.0, exposure_min_ms=exposure_s * 1e3,
                exposure_max_ms=exposure_s * 1e3, gain_max=1.0,
                illuminance_dome=REFERENCE_LUX * REFERENCE_EXPOSURE_S / exposure_s)
    base.update(changes)
    return SensorOptions(**base)


def sensor(options: SensorOptions, seed: int = 0) -> CameraSensor:
    return CameraSensor(options, CAMERA, "dome", PERIOD, np.random.default_rng(seed))


def wide_scene(s: CameraSensor, level: float = 0.1):
    """A uniform grey render of the sensor's render camera and a wall 4 m away."""
    wide = s.render_camera
    rgb = np.full((wide.height, wide.width, 3), round(level * 255), np.uint8)
    return rgb, np.full((wide.height, wide.width), 4.0, np.float32)


def column_profile(image: np.ndarray) -> np.ndarray:
    return image[40:80, :, 0].astype(float).mean(axis=0)


def test_blur_streak_is_speed_times_exposure_over_depth():
    exposure, speed, depth = 0.02, 3.0, 4.0
    s = sensor(quiet(exposure))
    rgb, z = wide_scene(s, 0.0)
    column = int(round(s.render_camera.cx))
    rgb[:, column] = 255  # one bright vertical line straight ahead
    still = s.capture(0.0, rgb, z, np.zeros(3), np.zeros(3))
    moving = s.capture(0.0, rgb, z, np.array([speed, 0.0, 0.0]), np.zeros(3))
    expected = CAMERA.fx * speed * exposure / depth  # 12 px
    profile = column_profile(moving.image)
    lit = np.flatnonzero(profile > 0.25 * profile.max())
    assert len(lit) == pytest.approx(expected, abs=2)
    # the light is spread, not lost: the streak holds the line's energy
    assert profile.sum() == pytest.approx(column_profile(still.image).sum(), rel=0.05)
    # the line moves left in the image as the camera moves right; the streak is centred on
    # the mid-exposure position, where the ideal render drew it
    centre = (profile * np.arange(len(profile))).sum() / profile.sum()
    assert centre == pytest.approx(CAMERA.cx, abs=0.75)


def test_a_still_camera_is_sharp_and_a_turning_one_blurs_by_rate_times_exposure():
    exposure, rate = 0.01, 1.0
    s = sensor(quiet(exposure))
    rgb, z = wide_scene(s, 0.0)
    rgb[:, int(round(s.render_camera.cx))] = 255
    assert (column_profile(s.capture(0.0, rgb, z, np.zeros(3), np.zeros(3)).image) > 60).sum() == 1
    turning = s.capture(0.0, rgb, z, np.zeros(3), np.array([0.0, rate, 0.0]))  # yaw: about y_C
    profile = column_profile(turning.image)
    lit = np.flatnonzero(profile > 0.25 * profile.max())
    assert len(lit) == pytest.approx(CAMERA.fx * rate * exposure, abs=1.5)


def test_rolling_shutter_shears_a_vertical_line_by_readout_times_image_speed():
    readout, speed, depth = 0.03, 2.0, 4.0
    s = sensor(quiet(1e-4, motion_blur=False, rolling_shutter_ms=readout * 1e3))
    rgb, z = wide_scene(s, 0.0)
    rgb[:, int(round(s.render_camera.cx))] = 255
    image = s.capture(0.0, rgb, z, np.array([speed, 0.0, 0.0]), np.zeros(3)).image
    top, bottom = image[5, :, 0].astype(float), image[-6, :, 0].astype(float)
    x = np.arange(CAMERA.width)
    top_u, bottom_u = (top * x).sum() / top.sum(), (bottom * x).sum() / bottom.sum()
    rows = CAMERA.height - 11
    # the image moves left at fx v / z; later rows are read later, so they see it further left
    expected = -CAMERA.fx * speed / depth * readout * rows / CAMERA.height
    assert bottom_u - top_u == pytest.approx(expected, abs=0.3)


def test_the_lens_images_a_ray_where_the_distortion_model_says():
    s = sensor(quiet(1e-3, distortion=(-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)))
    wide = s.render_camera
    assert wide.width > CAMERA.width and wide.height > CAMERA.height  # the corners see wider
    for ray in [(0.6, 0.4), (-0.9, 0.2), (0.3, -0.65)]:
        rgb, z = wide_scene(s, 0.0)
        u, v = wide.fx * ray[0] + wide.cx, wide.fy * ray[1] + wide.cy
        rgb[round(v) - 1:round(v) + 2, round(u) - 1:round(u) + 2] = 255
        ray = ((round(u) - wide.cx) / wide.fx, (round(v) - wide.cy) / wide.fy)
        image = s.capture(0.0, rgb, z, np.zeros(3), np.zeros(3)).image[..., 0].astype(float)
        rows, cols = np.indices(image.shape)
        seen = np.array([(image * cols).sum(), (image * rows).sum()]) / image.sum()
        expected = distort_points(CAMERA, s.lens.model.coefficients, np.array([ray]))[0]
        assert seen == pytest.approx(expected, abs=0.5)


def test_true_depth_follows_the_lens_with_the_image():
    s = sensor(quiet(1e-3))
    rgb, z = wide_scene(s)
    z[:, : s.render_camera.width // 2] = 2.0
    capture = s.capture(0.0, rgb, z, np.zeros(3), np.zeros(3))
    assert capture.depth.shape == (CAMERA.height, CAMERA.width)
    assert set(np.unique(capture.depth)) == {2.0, 4.0}


def test_vignetting_darkens_the_corners_to_the_configured_share():
    s = sensor(quiet(1e-3, corner_illumination=0.6))
    image = s.capture(0.0, *wide_scene(s, 0.8), np.zeros(3), np.zeros(3)).image[..., 1]
    centre = float(image[58:62, 78:82].mean())
    corner = float(image[0, 0])
    assert centre == pytest.approx(0.8 * 255, abs=1)
    assert corner / centre == pytest.approx(0.6, abs=0.01)


def test_noise_is_shot_and_read_noise_amplified_by_the_gain():
    full_well, read, level = 6000.0, 3.0, 0.2
    options = quiet(1e-3, full_well_electrons=full_well, read_noise_electrons=read)
    s = sensor(options)
    image = s.capture(0.0, *wide_scene(s, level), np.zeros(3), np.zeros(3)).image
    electrons = round(level * 255) / 255 * full_well
    expected_std = math.sqrt(electrons + read ** 2) * 255 / full_well
    assert image.std() == pytest.approx(expected_std, rel=0.1)
    assert image.mean() == pytest.approx(round(level * 255), abs=0.5)


def test_the_noise_of_a_frame_is_not_a_shifted_copy_of_the_last():
    """A sensor's noise is new in every frame. Drawn from one bank at one offset per frame, a
    frame's noise was the last one's moved whole by some shift, which Lucas-Kanade follows where
    the texture is faint: the realistic mine's map shrank by 4 % in a cruise with it (mine seed
    9, docs/vins.md, "The sensor noise's bank"). Over every shift of one frame against the next,
    the noise must correlate no more than independent noise does."""
    s = sensor(quiet(1e-3, full_well_electrons=6000.0, read_noise_electrons=3.0,
                     gain_max=8.0), seed=3)
    scene = wide_scene(s, 0.05)
    fields = []
    for k in range(8):
        image = s.capture(k * PERIOD, *scene, np.zeros(3), np.zeros(3)).image
        field = image.reshape(image.shape[0], -1).astype(float)  # rows of interleaved RGB
        fields.append(field - field.mean())
    h, w = fields[0].shape
    for a, b in zip(fields, fields[1:]):
        spectrum = np.fft.rfft2(a, (2 * h, 2 * w)) * np.conj(np.fft.rfft2(b, (2 * h, 2 * w)))
        correlation = np.fft.irfft2(spectrum, (2 * h, 2 * w))
        assert np.abs(correlation).max() / math.sqrt((a ** 2).sum() * (b ** 2).sum()) < 0.05


def moving_scene(s: CameraSensor, seed: int):
    """A random-textured render of the sensor's render camera, the depth sloping from 2 to
    8 m across it (so the blur's streaks differ pixel to pixel)."""
    wide = s.render_camera
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (wide.height, wide.width, 3), dtype=np.uint8)
    depth = np.tile(np.linspace(2.0, 8.0, wide.width, dtype=np.float32), (wide.height, 1))
    return rgb, depth


def test_a_frame_is_not_changed_by_the_next_capture():
    """The sensor reuses its working buffers frame to frame; what it delivers is the frame's
    own."""
    options = SensorOptions(time_offset_ms=0.0)
    s = sensor(options)
    twist = np.array([2.0, 0.0, 1.0]), np.array([0.0, 0.3, 0.0])
    first = s.capture(0.0, *moving_scene(s, 1), *twist)
    image, depth = first.image.copy(), first.depth.copy()
    second = s.capture(0.05, *moving_scene(s, 2), *twist)
    assert not np.array_equal(second.image, image)
    np.testing.assert_array_equal(first.image, image)
    np.testing.assert_array_equal(first.depth, depth)


def test_auto_exposure_recovers_from_a_darkening_after_its_delay_then_raises_gain():
    options = SensorOptions(time_offset_ms=0.0, timestamp_jitter_ms=0.0, drop_probability=0.0,
                            distortion=(), corner_illumination=1.0, read_noise_electrons=0.0,
                            full_well_electrons=1e9, motion_blur=False,
                            exposure_delay_frames=2, exposure_rate=0.5)
    s = sensor(options)
    bright = wide_scene(s, 0.5)
    first = s.capture(0.0, *bright, np.zeros(3), np.zeros(3))
    assert first.image.mean() / 255 == pytest.approx(options.exposure_target, rel=0.02)
    dark = wide_scene(s, 0.005)  # a hundred times darker: past the longest exposure
    means, gains = [], []
    for _ in range(40):
        capture = s.capture(0.0, *dark, np.zeros(3), np.zeros(3))
        means.append(capture.image.mean() / 255)
        gains.append(capture.exposure.gain)
    # the first frames keep the old exposure (the delay), then it climbs back
    assert means[0] == pytest.approx(means[2], rel=0.05)
    assert means[0] < 0.05
    assert means[3] > means[2]
    assert means[-1] == pytest.approx(options.exposure_target, rel=0.05)
    assert capture.exposure.time_s == pytest.approx(options.exposure_max_ms * 1e-3)
    assert gains[-1] > 1.0 and gains[0] == 1.0


def test_stamps_are_late_by_the_hidden_offset_with_jitter_and_some_frames_are_lost():
    options = SensorOptions(time_offset_ms=15.0, timestamp_jitter_ms=1.0, drop_probability=0.05,
                            distortion=(), motion_blur=False)
    s = sensor(options, seed=3)
    scene = wide_scene(s)
    stamps = [s.capture(k * PERIOD, *scene, np.zeros(3), np.zeros(3)).stamp
              for k in range(600)]
    lost = sum(stamp is None for stamp in stamps)
    late = np.array([stamp - k * PERIOD for k, stamp in enumerate(stamps) if stamp is not None])
    assert late.mean() == pytest.approx(0.015, abs=2e-4)
    assert late.std() == pytest.approx(0.001, rel=0.15)
    assert 10 <= lost <= 55  # 30 expected; binomial 600 x 0.05 within about 4 sigma


def test_an_offset_as_long_as_the_frame_period_is_refused():
    # 15 ms late and 1 ms jitter do not fit a 60 Hz camera's 16.7 ms period
    with pytest.raises(ValueError, match="frame period"):
        CameraSensor(SensorOptions(), CAMERA, "dome", 1.0 / 60.0, np.random.default_rng(0))


def test_the_true_mounting_is_off_by_the_configured_calibration_error():
    options = SensorOptions(mount_rotation_error_deg=0.5, mount_translation_error_mm=5.0)
    head = CameraHead(CAMERA, 20.0, sensor=options, world="dome", rng=np.random.default_rng(1))
    error = np.linalg.inv(head.T_B_C_configured) @ head.T_B_C
    assert math.degrees(np.linalg.norm(so3_log(error[:3, :3]))) == pytest.approx(0.5)
    assert np.linalg.norm(error[:3, 3]) == pytest.approx(0.005)
    ideal = CameraHead(CAMERA, 20.0)
    assert np.array_equal(ideal.T_B_C, ideal.T_B_C_configured)


def test_a_vehicle_keeps_its_mounting_from_flight_to_flight():
    """The mounting error comes from the vehicle's generator; the noise and stamps from the
    flight's, as they would without one."""
    options = SensorOptions(distortion=(), motion_blur=False)

    def head(flight, vehicle=None):
        return CameraHead(CAMERA, 20.0, sensor=options, world="dome",
                          rng=np.random.default_rng(flight),
                          vehicle_rng=None if vehicle is None else np.random.default_rng(vehicle))

    def stamps(h):
        scene = wide_scene(h.sensor)
        return [h.sensor.capture(k * PERIOD, *scene, np.zeros(3), np.zeros(3)).stamp
                for k in range(20)]

    alone, other_vehicle = head(1), head(2)
    assert np.array_equal(head(1, vehicle=1).T_B_C, alone.T_B_C)
    other_flight = head(2, vehicle=1)
    assert np.array_equal(other_flight.T_B_C, alone.T_B_C)
    assert not np.array_equal(other_vehicle.T_B_C, alone.T_B_C)
    assert stamps(other_flight) == stamps(other_vehicle) != stamps(alone)


def test_a_simulated_flight_mounts_the_camera_of_the_configured_vehicle():
    from companion.config import load_config
    from drivers.sim.host import camera_head

    def mounting(seed, *overrides):
        config = load_config(None, ["sim.profile=realistic", *overrides])
        return camera_head(config, "dome", seed).T_B_C

    assert np.array_equal(mounting(4, "sim.vehicle_seed=9"), mounting(9))
    assert np.array_equal(mounting(4, "sim.noise_seed=9"), mounting(4))  # noise alone
    assert not np.array_equal(mounting(4), mounting(9))


def test_camera_twist_of_a_yawing_vehicle_includes_the_lever_arm():
    from drivers.sim.camera import T_BODY_CAMERA
    from drivers.sim.quadrotor import VehicleState
    state = VehicleState(0.0, np.zeros(3), np.zeros(3), rot_to_quat(np.eye(3)),
                         np.array([0.0, 0.0, 1.0]), np.zeros(3), False)
    v_C, w_C = camera_twist(state, T_BODY_CAMERA)
    # yawing left at 1 rad/s, a camera 10 cm ahead moves left at 0.1 m/s: -x in the optical
    # frame (x right); the rotation is about the optical -y axis (y down)
    assert v_C == pytest.approx([-0.1, 0.0, 0.0], abs=1e-12)
    assert w_C == pytest.approx([0.0, -1.0, 0.0], abs=1e-12)


@pytest.mark.parametrize("changes, key", [
    (dict(exposure_min_ms=40.0), "exposure_min_ms"),
    (dict(distortion=(0.1, 0.2)), "distortion"),
    (dict(drop_probability=1.0), "drop_probability"),
    (dict(corner_illumination=0.0), "corner_illumination"),
])
def test_bad_options_name_the_key(changes, key):
    with pytest.raises(OptionError, match=key):
        SensorOptions(**changes)


def test_a_world_without_a_light_level_is_named():
    with pytest.raises(ValueError, match="illuminance_mine"):
        SensorOptions().illuminance("moon")


def test_an_ideal_head_delivers_the_render_unchanged():
    class Renderer:
        camera = CAMERA

        def render(self, T_W_C):
            self.pose = T_W_C
            return np.full((120, 160, 3), 7, np.uint8), np.ones((120, 160), np.float32)
    from drivers.sim.quadrotor import VehicleState
    state = VehicleState(0.0, np.array([1.0, 2.0, 3.0]), np.zeros(3),
                         rot_to_quat(np.eye(3)), np.zeros(3), np.zeros(3), False)
    head, renderer = CameraHead(CAMERA, 20.0), Renderer()
    capture = head.shoot(renderer, 0.25, state)
    assert capture.stamp == 0.25 and (capture.image == 7).all()
    assert np.allclose(renderer.pose[:3, 3], [1.0, 2.0, 3.0] + head.T_B_C[:3, 3])
    assert head.model.is_pinhole


def test_a_realistic_recording_has_the_lens_late_stamps_aligned_depth_and_the_cameras_truth(
        tmp_path):
    """The estimator is given the configured mounting and the stamps; the evaluation is also
    given the truth they hide (``cam0/truth.*``)."""
    from drivers.camera.options import CameraOptions
    from drivers.sim.imu import ImuOptions
    from drivers.sim.options import SimOptions
    from drivers.sim.quadrotor import VehicleOptions
    from drivers.sim.record import record_dataset
    camera = CameraOptions(width=160, height=120)
    record_dataset(tmp_path, SimOptions(world="dome", seed=2, profile="realistic"), camera,
                   VehicleOptions(), ImuOptions(), duration=1.0,
                   sim_camera=SensorOptions(drop_probability=0.0, timestamp_jitter_ms=0.0))
    stream = read_camera(tmp_path)
    assert stream.distortion == pytest.approx(SensorOptions().distortion)
    assert np.allclose(stream.T_B_C, camera.T_B_C())  # the configured mounting, not the true
    offsets = (stream.t_ns - np.arange(len(stream.t_ns)) * 50_000_000) * 1e-9
    assert offsets == pytest.approx(0.015, abs=1e-6)
    depth = read_camera(tmp_path, "depth0")
    assert np.array_equal(depth.t_ns, stream.t_ns)
    truth = read_camera_truth(tmp_path, stream)
    assert truth.exposed_ns.tolist() == (np.arange(len(stream.t_ns)) * 50_000_000).tolist()
    off = np.linalg.inv(camera.T_B_C()) @ truth.T_B_C
    assert math.degrees(np.linalg.norm(so3_log(off[:3, :3]))) == pytest.approx(0.5)
    assert np.linalg.norm(off[:3, 3]) == pytest.approx(0.005)


def test_a_switched_off_sensor_leaves_the_realistic_world_and_imu_with_an_exact_camera(
        tmp_path):
    """``[sim_camera] enabled = false``: the ablation of the camera alone."""
    from drivers.camera.options import CameraOptions
    from drivers.sim.imu import ImuOptions
    from drivers.sim.options import SimOptions
    from drivers.sim.quadrotor import VehicleOptions
    from drivers.sim.record import record_dataset
    off = SensorOptions(enabled=False)
    assert off.for_profile("realistic") is None and SensorOptions().for_profile("ideal") is None
    assert SensorOptions().for_profile("realistic") == SensorOptions()
    runs = {}
    for name, sensor in (("off", off), ("on", SensorOptions()), ("ideal", None)):
        profile = "ideal" if name == "ideal" else "realistic"
        record_dataset(tmp_path / name, SimOptions(world="mine", seed=1, profile=profile),
                       CameraOptions(width=160, height=120), VehicleOptions(), ImuOptions(),
                       duration=0.5, sim_camera=sensor)
        runs[name] = (read_camera(tmp_path / name), read_imu(tmp_path / name))
    stream, imu = runs["off"]
    assert stream.distortion == pytest.approx((0.0,) * 4)
    assert stream.t_ns.tolist() == (np.arange(len(stream.t_ns)) * 50_000_000).tolist()
    # The IMU is the realistic one, sample for sample, and the world the realistic one (the
    # mine's dust): the image is not the ideal world's.
    assert np.array_equal(imu.accel, runs["on"][1].accel)
    assert not np.array_equal(imu.accel, runs["ideal"][1].accel)
    last, ideal_last = (cv2.imread(str(runs[name][0].paths[-1])) for name in ("off", "ideal"))
    assert not np.array_equal(last, ideal_last)


def _deliveries(head: CameraHead, frames: int) -> list[tuple[float, float]]:
    """``(frame.t, clock when it arrived)`` of the first ``frames`` of ``head`` on a lockstep
    clock stepped at 200 Hz, as the simulator steps it."""
    import asyncio

    from drivers.clock import SimClock
    from drivers.sim.camera import SimCamera
    from drivers.sim.faults import FaultSchedule
    from drivers.sim.quadrotor import Quadrotor

    class Vehicle:  # what SimCamera reads of the simulated vehicle
        vehicle = Quadrotor(position=(0.0, 0.0, 1.5))
        faults = FaultSchedule(())
        time = 0.0

    class Renderer:
        camera = head.render_camera

        def render(self, T_W_C, alpha=False):
            shape = (self.camera.height, self.camera.width)
            return (np.full((*shape, 4 if alpha else 3), 60, np.uint8),
                    np.full(shape, 4.0, np.float32))

    clock = SimClock(0.0)
    camera = SimCamera(Vehicle(), Renderer(), clock, head)

    async def main():
        async def step():
            for k in range(1, 400):
                await asyncio.sleep(0)
                clock.advance_to(k * 0.005)
        stepping = asyncio.create_task(step())
        arrivals = []
        for _ in range(frames):
            frame = await camera.next_frame()
            arrivals.append((frame.t, clock.now()))
        stepping.cancel()
        return arrivals
    return asyncio.run(main())


def _after_grid(t: float) -> float:
    """How long after the last multiple of the 50 ms frame period ``t`` is."""
    return t - math.floor(t / 0.05 + 1e-9) * 0.05


def test_an_ideal_camera_delivers_each_frame_at_its_exposure_tick():
    # exposed at the first physics tick at or after each frame time, and handed over at that
    # very tick, not one later: the ideal profile keeps a lockstep flight's timing
    deliveries = _deliveries(CameraHead(CAMERA, 20.0), 4)
    for t, arrived in deliveries:
        assert arrived == t and _after_grid(t) <= 0.005 + 1e-9
    assert len({round(t / 0.05) for t, _ in deliveries}) == 4


def test_a_late_stamped_frame_arrives_at_its_stamp():
    options = SensorOptions(time_offset_ms=15.0, timestamp_jitter_ms=0.0, drop_probability=0.0)
    head = CameraHead(CAMERA, 20.0, sensor=options, world="dome", rng=np.random.default_rng(0))
    for t, arrived in _deliveries(head, 4):
        assert arrived == pytest.approx(t, abs=1e-9)  # handed over at its stamp
        assert _after_grid(t - 0.015) <= 0.005 + 1e-9  # 15 ms after its exposure tick
