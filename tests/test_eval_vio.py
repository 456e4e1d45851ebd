"""`companion eval vio`: unusable datasets are named in one line, the frames are fed as in
flight, and the scoring gives the known answers for a trace with known errors (the true pose
moved by a fixed rigid motion, landmarks 10 % too deep)."""

import dataclasses
import json
import math
import shutil

import cv2
import gtsam
import numpy as np
import pytest

from autonomy.geometry import PinholeCamera, make_pose, rot_to_quat, rot_z, so3_exp
from autonomy.lens import CameraModel, Rectifier
from autonomy.messages import SparseMap
from autonomy.vins.options import VinsOptions
from autonomy.vins.static_init import StaticInit
from companion.cli import main
from companion.tools.eval import vio
from companion.tools.eval.vio import (
    EvaluationError, ImuFeed, KeyframeEstimate, Rebuild, VioTrace, build_vins, depth_relative_errors,
    evaluate_vio, format_vio_report, read_vio_dataset, run_vins, score_vio, vio_frames,
)
from companion.tools.eval.vio_bound import FactorLog, batch_positions
from drivers.dataset.euroc import EurocWriter, read_depth_png

NOISE = {"rate_hz": 200.0, "gyroscope_noise_density": 1e-4, "gyroscope_random_walk": 1e-5,
         "accelerometer_noise_density": 1e-3, "accelerometer_random_walk": 1e-4}
T0_NS = 1_403_715_273_262_142_976  # a EuRoC-sized epoch: float seconds would lose the ns
CAMERA = PinholeCamera.from_hfov(32, 24, 1.5)
GYRO_BIAS = np.array([0.01, 0.0, 0.0])


def _position(t: float) -> np.ndarray:
    """A climbing helix of radius 3 m."""
    return np.array([3.0 * math.cos(t), 3.0 * math.sin(t), 0.5 * t])


def _write_dataset(root, seconds: float = 4.0, image_size: tuple[int, int] = (24, 32),
                   late_frame: bool = False, distortion=(0.0, 0.0, 0.0, 0.0)):
    """IMU and ground truth at 200 Hz, frames with a 2 m depth image (NaN on the left 4
    columns) at 20 Hz; ``late_frame``: one more frame 15 ms after the last sample, as a camera
    stamping late delivers."""
    rng = np.random.default_rng(0)
    depth = np.full((24, 32), 2.0, dtype=np.float32)
    depth[:, :4] = np.nan
    with EurocWriter(root, CAMERA, np.eye(4), 20.0, NOISE, distortion) as writer:
        for k in range(int(seconds * 200) + 1):
            t_ns, t = T0_NS + 5_000_000 * k, 0.005 * k
            writer.add_imu(t_ns, [0.0, 0.0, 1.0], [0.0, 0.0, 9.8])
            writer.add_groundtruth(t_ns, _position(t), rot_to_quat(rot_z(t)), [0.0] * 3,
                                   GYRO_BIAS, [0.0] * 3)
            if k % 10 == 0:
                writer.add_frame(t_ns, rng.integers(0, 256, (*image_size, 3), dtype=np.uint8),
                                 depth)
        if late_frame:
            writer.add_frame(t_ns + 15_000_000,
                             rng.integers(0, 256, (*image_size, 3), dtype=np.uint8), depth)


def _landmark_errors(data) -> np.ndarray:
    """The depth errors of five landmarks at 2.2 m against the dataset's first depth image:
    two usable, one untracked, one on unknown depth, one off the image."""
    pixels = np.array([[10.0, 10.0], [20.2, 5.4], [10.0, 10.0], [1.0, 1.0], [-5.0, 3.0]])
    sparse = SparseMap(0.0, np.arange(5), np.column_stack([np.zeros((5, 2)), [2.2] * 5]),
                       np.full(5, 0.1), pixels, np.array([True, True, False, True, True]))
    return depth_relative_errors(sparse, read_depth_png(next(iter(data.depth.values()))))


def _known_trace(data, frames: int) -> VioTrace:
    """A trace with no pose for 5 frames, then the true pose moved by a fixed rigid motion, a
    keyframe every other frame, and the landmarks of :func:`_landmark_errors`; initialised
    at 1 s with the up-vector 0.5 deg off and the gyro bias 10 % too large."""
    R, offset = so3_exp(np.array([0.2, -0.1, 1.0])), np.array([5.0, -2.0, 1.0])
    t = [0.05 * k for k in range(frames)]
    posed = [k >= 5 for k in range(frames)]
    up = so3_exp(np.radians([0.5, 0.0, 0.0])) @ [0.0, 0.0, 1.0]
    init = StaticInit(np.eye(3), 1.1 * GYRO_BIAS, up, 9.8, 0.0, 1.0, 200, 0.0, 0.0)
    return VioTrace(
        t=t,
        positions=[R @ _position(tk) + offset if p else None for tk, p in zip(t, posed)],
        keyframe=[p and k % 2 == 1 for k, p in enumerate(posed)],
        frontend_ms=[0.1 * k for k in range(frames)],
        backend_ms=[10.0 if k % 2 == 1 else 0.5 for k in range(frames)],
        health=["TRACKING" if p else "INITIALISING" for p in posed],
        depth_errors=[_landmark_errors(data) for p in posed if p],
        static_init=init, resets=2)


def test_landmarks_are_compared_only_where_tracked_seen_and_known(tmp_path):
    _write_dataset(tmp_path, seconds=0.1)
    errors = _landmark_errors(read_vio_dataset(tmp_path))
    assert errors == pytest.approx([0.1, 0.1], rel=1e-6)


def test_a_rigidly_moved_ground_truth_scores_zero_error_and_the_known_offsets(tmp_path):
    _write_dataset(tmp_path)
    data = read_vio_dataset(tmp_path)
    result = score_vio(_known_trace(data, 81), data)
    assert result["frames"] == 81 and result["keyframes"] == 38 and result["resets"] == 2
    assert result["ate_rmse_m"] < 1e-6 and result["scale_error"] < 1e-6
    assert result["ate_sim3_rmse_m"] < 1e-6
    tracked = [_position(0.05 * k) for k in range(5, 81)]
    assert result["distance_m"] == pytest.approx(
        np.sum(np.linalg.norm(np.diff(tracked, axis=0), axis=1)))
    assert result["depth_rel_err_median"] == pytest.approx(0.1, rel=1e-3)
    assert result["depth_points"] == 2 * 76
    assert result["frontend_ms_median"] == pytest.approx(4.0)
    assert result["backend_ms_median"] == 10.0 and result["backend_ms_p95"] == 10.0
    assert result["health"] == {"INITIALISING": 5, "TRACKING": 76}
    assert result["init"]["t"] == 1.0
    assert result["init"]["gravity_err_deg"] == pytest.approx(0.5)
    assert result["init"]["gyro_bias_err_rel"] == pytest.approx(0.1)
    assert json.loads(json.dumps(result)) == result
    assert "ATE 0.000 m" in format_vio_report(result)


def test_the_estimated_mounting_is_reported_as_its_offset_in_the_cameras_axes(tmp_path):
    _write_dataset(tmp_path)
    data = read_vio_dataset(tmp_path)
    trace = _known_trace(data, 81)
    assert score_vio(trace, data)["camera_mounting"] is None  # not estimated
    offset = make_pose(so3_exp(np.radians([0.3, 0.1, -0.2])), np.array([0.001, 0.002, -0.003]))
    trace.camera_mounting = data.camera.T_B_C @ offset
    result = score_vio(trace, data)
    np.testing.assert_allclose(result["camera_mounting"]["rotation_deg"], [0.3, 0.1, -0.2],
                               atol=1e-9)
    np.testing.assert_allclose(result["camera_mounting"]["translation_mm"], [1.0, 2.0, -3.0],
                               atol=1e-9)
    assert "rotation (+0.300 +0.100 -0.200) deg, position (+1.0 +2.0 -3.0) mm" in \
        format_vio_report(result)


def _keyframes_in_a_yawed_world(errors_body, velocity_error, *, pose_sigma=0.01,
                                velocity_sigma=0.01, count=20):
    """Keyframes every 0.1 s whose world is the truth's turned 0.7 rad about z and shifted
    (the gauge), each off the truth by ``errors_body(k)`` in its body frame (rotation, then
    position) and by ``velocity_error`` in velocity (the truth is still)."""
    T_W_G = make_pose(rot_z(0.7), np.array([5.0, -2.0, 1.0]))
    keyframes = []
    for k in range(count):
        t = 0.1 * (k + 1)
        true = T_W_G @ make_pose(rot_z(t), _position(t))
        error = errors_body(k)
        R = true[:3, :3] @ so3_exp(-error[:3])
        estimate = make_pose(R, true[:3, 3] - R @ error[3:])
        keyframes.append(KeyframeEstimate(t, estimate, np.asarray(velocity_error, float),
                                          pose_sigma**2 * np.eye(6),
                                          velocity_sigma**2 * np.eye(3), np.zeros(3), 40,
                                          GYRO_BIAS))
    return keyframes


def test_the_nees_is_measured_from_the_first_keyframe_not_from_a_best_fit(tmp_path):
    """Through the gauge (yaw and shift) the first keyframe is exact; every later one is off
    by 2 and 1 cm in its body frame: a pose NEES of (0.02^2 + 0.01^2) / 0.01^2 = 5, which a
    best fit of the whole path would hide. The velocity, 3 cm/s off in x: 9."""
    _write_dataset(tmp_path, seconds=2.5)
    data = read_vio_dataset(tmp_path)
    offset = np.array([0.0, 0.0, 0.0, 0.02, 0.0, -0.01])
    trace = _known_trace(data, 41)
    trace.keyframes = _keyframes_in_a_yawed_world(lambda k: offset if k else 0 * offset,
                                                  [0.03, 0.0, 0.0])
    result = score_vio(trace, data)
    assert result["nees_keyframes"] == 20 and result["nees_refused"] == 0
    assert result["nees_pose_median"] == pytest.approx(5.0, rel=1e-6)
    assert result["nees_pose_mean"] == pytest.approx(5.0 * 19 / 20, rel=1e-6)
    assert result["nees_velocity_mean"] == pytest.approx(9.0, rel=1e-6)
    assert result["nees_pose_by_axis"] == pytest.approx([0, 0, 0, 3.8, 0, 0.95], abs=1e-6)
    assert "5.0 median (6 if the covariance is honest)" in format_vio_report(result)


def test_the_heading_drift_is_the_last_keyframes_yaw_error_through_the_gauge(tmp_path):
    """The first keyframe fixes the gauge (yaw and shift); the yaw error grows to 0.3 deg, and
    a roll error beside it is not heading."""
    _write_dataset(tmp_path, seconds=2.5)
    data = read_vio_dataset(tmp_path)
    trace = _known_trace(data, 41)
    trace.keyframes = _keyframes_in_a_yawed_world(
        lambda k: np.r_[np.radians([0.2, 0.0, -0.3 * k / 19]), np.zeros(3)], [0.0] * 3)
    late = dataclasses.replace(trace.keyframes[-1], t=99.0)  # a stamp past the truth's end
    trace.keyframes.append(late)
    result = score_vio(trace, data)
    # the error is the body's: estimate = truth Exp(-error), so -0.3 deg about z turns it +0.3
    assert result["heading_drift_deg"] == pytest.approx(0.3, abs=2e-3)
    assert "heading drift +0.30 deg" in format_vio_report(result)


def test_the_gyro_bias_is_scored_per_axis_against_the_truth(tmp_path):
    """Keyframes whose gyro bias is the truth's (0.01 rad/s about x) plus 1 mrad/s about z:
    0.0573 deg/s of mean error about z alone, which over the 1.9 s between the first and the
    last keyframe turns the heading the other way, by 0.109 deg."""
    _write_dataset(tmp_path, seconds=2.5)
    data = read_vio_dataset(tmp_path)
    trace = _known_trace(data, 41)
    trace.keyframes = [dataclasses.replace(kf, gyro_bias=kf.gyro_bias + [0.0, 0.0, 1e-3])
                       for kf in _keyframes_in_a_yawed_world(lambda k: np.zeros(6), [0.0] * 3)]
    bias = score_vio(trace, data)["gyro_bias"]
    z_error = math.degrees(1e-3)
    np.testing.assert_allclose(bias["mean_error"], [0.0, 0.0, z_error], atol=1e-9)
    np.testing.assert_allclose(bias["rms_error"], [0.0, 0.0, z_error], atol=1e-9)
    np.testing.assert_allclose(bias["true_mean"], np.degrees(GYRO_BIAS), atol=1e-9)
    assert bias["heading_deg"] == pytest.approx(-1.9 * z_error)
    assert bias["error_by_time"] == []  # no whole 8 s window in 2 s
    assert "mean error (+0.0000, +0.0000, +0.0573) deg/s" in format_vio_report(
        score_vio(trace, data))


def test_the_end_error_is_split_through_the_first_keyframes_gauge(tmp_path):
    """An estimate whose path is the truth's 2 % longer and turned 0.5 deg left about the
    first keyframe, in a world yawed off the truth's (the gauge): scale 1.02 and bearing
    +0.5 deg over the path, which the ATE's best fit would have turned away."""
    _write_dataset(tmp_path, seconds=2.5)
    data = read_vio_dataset(tmp_path)
    trace = _known_trace(data, 41)
    exact = _keyframes_in_a_yawed_world(lambda k: np.zeros(6), [0.0] * 3)
    start = exact[0].T_W_B[:3, 3]
    turn = rot_z(math.radians(0.5))
    trace.keyframes = [dataclasses.replace(kf, T_W_B=make_pose(
        kf.T_W_B[:3, :3], start + 1.02 * turn @ (kf.T_W_B[:3, 3] - start))) for kf in exact]
    split = score_vio(trace, data)["end_split"]
    assert split["scale"] == pytest.approx(1.02) and split["bearing_deg"] == pytest.approx(0.5)
    assert split["start_m"] == pytest.approx(0.0, abs=1e-9)
    flown = np.linalg.norm((exact[-1].T_W_B[:3, 3] - start)[:2])
    assert split["distance_m"] == pytest.approx(flown)
    assert split["across_m"] == pytest.approx(1.02 * flown * math.sin(math.radians(0.5)))
    assert "path scale 1.0200" in format_vio_report(score_vio(trace, data))


def test_the_gyro_bias_by_time_skips_windows_without_a_keyframe(tmp_path):
    """Keyframes to 0.5 s with the truth's bias, none from there to 1.65 s (a loss), then
    1 mrad/s off about z: 0.3 s windows give the error where keyframes are and nothing in the
    gap, and the trapezoid across the gap turns 0.9 mrad of heading."""
    _write_dataset(tmp_path, seconds=2.5)
    data = read_vio_dataset(tmp_path)
    trace = _known_trace(data, 41)
    kept = [kf for kf in _keyframes_in_a_yawed_world(lambda k: np.zeros(6), [0.0] * 3)
            if kf.t < 0.55 or kf.t > 1.65]
    trace.keyframes = [kf if kf.t < 1.0 else dataclasses.replace(
        kf, gyro_bias=kf.gyro_bias + [0.0, 0.0, 1e-3]) for kf in kept]
    truth_t = vio._seconds(data.truth.t_ns, data.imu.t_ns[0])
    bias = vio._gyro_bias_metrics(trace.keyframes, truth_t, data.truth, window_s=0.3)
    assert [w["t"] for w in bias["error_by_time"]] == pytest.approx([0.1, 0.4, 1.6])
    assert [w["mean_error"][2] for w in bias["error_by_time"]] == pytest.approx(
        [0.0, 0.0, math.degrees(1e-3)])
    assert bias["heading_deg"] == pytest.approx(-math.degrees(0.9e-3))


def test_a_trace_without_keyframes_has_no_gyro_bias_score(tmp_path):
    _write_dataset(tmp_path, seconds=2.5)
    data = read_vio_dataset(tmp_path)
    trace = _known_trace(data, 41)
    trace.keyframes = []
    result = score_vio(trace, data)
    assert result["gyro_bias"] is None and result["end_split"] is None
    assert "gyro bias against the truth (x, y, z): too few keyframes" in format_vio_report(result)


def test_the_scale_taken_out_leaves_the_paths_shape(tmp_path):
    """An estimate 3 % short has an ATE but none once the similarity takes the scale out."""
    _write_dataset(tmp_path)
    data = read_vio_dataset(tmp_path)
    trace = _known_trace(data, 81)
    trace.positions = [None if p is None else 0.97 * p for p in trace.positions]
    result = score_vio(trace, data)
    assert result["ate_rmse_m"] > 1e-3 and result["ate_sim3_rmse_m"] < 1e-6


def test_a_keyframe_with_an_unusable_covariance_is_counted_not_scored(tmp_path):
    _write_dataset(tmp_path, seconds=2.5)
    data = read_vio_dataset(tmp_path)
    trace = _known_trace(data, 41)
    keyframes = _keyframes_in_a_yawed_world(lambda k: np.zeros(6), [0.0, 0.0, 0.0], count=3)
    trace.keyframes = keyframes[:2] + [KeyframeEstimate(
        keyframes[2].t, keyframes[2].T_W_B, keyframes[2].velocity_W,
        np.full((6, 6), np.nan), np.eye(3), np.zeros(3), 40, GYRO_BIAS)]
    result = score_vio(trace, data)
    assert result["nees_keyframes"] == 2 and result["nees_refused"] == 1
    assert result["nees_pose_mean"] == pytest.approx(0.0, abs=1e-12)


def test_a_rebuild_is_reported_with_the_window_just_before_it(tmp_path):
    """What a rebuild's record says (docs/vins.md, the resets): the variable GTSAM named, and
    the last keyframe before it, whose sigmas, landmarks, speed and bias errors are known."""
    _write_dataset(tmp_path, seconds=2.5)
    data = read_vio_dataset(tmp_path)
    trace = _known_trace(data, 41)
    trace.keyframes = _keyframes_in_a_yawed_world(lambda k: np.zeros(6), [0.0, 0.03, 0.04],
                                                  pose_sigma=0.2, count=5)
    before = dataclasses.replace(trace.keyframes[-1], accel_bias=np.array([0.0, 0.0, 0.05]))
    failure = ("Indeterminate linear system detected while working near variable\n"
               "8646911284551352643 (Symbol: x323).")
    trace.rebuilds = [Rebuild(0.6, failure, before), Rebuild(0.05, "update refused", None)]
    first, second = score_vio(trace, data)["rebuilds"]
    assert first["t"] == 0.6 and first["variable"] == "x323" and first["landmarks"] == 40
    assert first["position_sigma_m"] == pytest.approx(0.2 * math.sqrt(3))
    assert first["yaw_sigma_deg"] == pytest.approx(math.degrees(0.2))
    assert first["speed_error_m_s"] == pytest.approx(0.05)  # the truth is still
    assert first["accel_bias_error_m_s2"] == pytest.approx(0.05)
    assert "rebuild at t=0.60 s near x323: before it 40 landmarks, position sigma 0.346 m, " \
           "speed error +0.050 m/s" in format_vio_report(score_vio(trace, data))
    assert second == {"t": 0.05, "variable": None, "position_sigma_m": None,
                      "yaw_sigma_deg": None, "landmarks": None, "speed_error_m_s": None,
                      "accel_bias_error_m_s2": None}


def test_too_few_poses_give_no_trajectory_error_and_say_why(tmp_path):
    _write_dataset(tmp_path, seconds=0.3)
    data = read_vio_dataset(tmp_path)
    result = score_vio(_known_trace(data, 6), data)
    assert result["frames"] == 6 and result["ate_rmse_m"] is None
    assert result["note"] == ("no trajectory error from 1 poses: alignment needs at least 3 "
                              "points, got 1")
    assert "n/a" in format_vio_report(result)


def test_no_initialisation_and_no_keyframes_score_as_none(tmp_path):
    _write_dataset(tmp_path, seconds=0.3)
    result = score_vio(VioTrace(t=[0.0], positions=[None], keyframe=[False], frontend_ms=[1.0],
                                backend_ms=[1.0], health=["INITIALISING"]),
                       read_vio_dataset(tmp_path))
    assert result["init"] is None and result["backend_ms_p95"] is None
    assert result["nees_pose_mean"] is None and result["nees_keyframes"] == 0
    assert result["depth_rel_err_median"] is None and result["depth_points"] == 0
    assert "init: none" in format_vio_report(result)


def test_each_frame_comes_after_every_imu_sample_up_to_its_time_and_its_exposure(tmp_path):
    _write_dataset(tmp_path, seconds=1.0)
    data = read_vio_dataset(tmp_path)
    frames = list(vio_frames(data, max_frames=5))
    assert [frame.t for frame in frames] == pytest.approx([0.0, 0.05, 0.1, 0.15, 0.2])
    for frame, path in zip(frames, data.camera.paths):
        assert frame.image.shape == (24, 32, 3) and frame.image.dtype == np.uint8
        assert np.array_equal(frame.image, cv2.imread(str(path))[..., ::-1])  # RGB, not BGR
        assert frame.depth_path is not None and frame.depth_path.is_file()
    # A camera stamping 15 ms late (td > 0) is exposed before its stamp: the IMU up to the
    # stamp. One stamping 15 ms early (td < 0) is exposed after it: the IMU up to the exposure.
    for offset, ahead in ((0.015, 0.0), (-0.015, 0.015)):
        vins = build_vins(data, VinsOptions(time_offset_s=offset))
        fed, feed = [], ImuFeed(data)
        vins.add_imu = lambda sample: fed.append(sample.t)  # noqa: E731 (what reaches it)
        for frame in frames:
            feed.before_frame(vins, frame.t)
            assert frame.t + ahead - 0.005 < fed[-1] <= frame.t + ahead + 1e-9
        assert fed == pytest.approx([0.005 * i for i in range(len(fed))])  # each once, in order


def test_a_frame_stamped_after_the_ground_truth_ends_is_run(tmp_path):
    """A late-stamping camera's last frame can pass the last ground-truth sample: the VINS
    takes it, and the track error, which needs the true pose, skips it."""
    _write_dataset(tmp_path, seconds=1.0, late_frame=True)
    result = evaluate_vio(tmp_path, VinsOptions(), consistency=False)
    assert result["frames"] == 22
    assert {"track_error_px_median", "track_error_px_p90", "track_error_by_age"} <= set(result)


LENS = (-0.28, 0.07, 2e-4, 2e-5)


def test_rectified_the_frames_and_depth_are_the_flight_applications_and_the_lens_is_gone(
        tmp_path):
    """With ``rectify`` the VINS sees each frame as the flight application's rectifier makes it
    (the lens undone onto the pinhole of its intrinsics) and the depth images moved alike; the
    camera it is built for has no distortion left. A recording without distortion is left as it
    is."""
    _write_dataset(tmp_path, seconds=0.2, distortion=LENS)
    raw = read_vio_dataset(tmp_path)
    data = vio.rectified(raw)
    assert not any(data.camera.distortion) and data.camera.camera == raw.camera.camera
    rectify = Rectifier(CameraModel(CAMERA, "radtan", LENS), CAMERA)
    for frame, raw_frame in zip(vio_frames(data), vio_frames(raw)):
        assert np.array_equal(frame.image, rectify(raw_frame.image))
        truth = read_depth_png(frame.depth_path)
        np.testing.assert_array_equal(vio.read_frame_depth(frame.depth_path, data),
                                      rectify.depth(truth))
    assert not np.array_equal(frame.image, raw_frame.image)  # the lens did move pixels
    _write_dataset(tmp_path / "pinhole", seconds=0.2)
    pinhole = read_vio_dataset(tmp_path / "pinhole")
    assert vio.rectified(pinhole) is pinhole


def test_eval_vio_rectify_runs_on_a_distorted_recording_and_truth_tracks_stay_refused(
        tmp_path, capsys):
    """``--rectify`` scores a distorted recording through the rectifier; truth tracks still
    need a recording made through an exact camera, rectified or not."""
    _write_dataset(tmp_path, seconds=1.0, distortion=LENS)
    status, captured = _eval_vio(capsys, tmp_path, "--rectify", "--json")
    assert status == 0 and json.loads(captured.out)["frames"] == 21
    status, captured = _eval_vio(capsys, tmp_path, "--rectify", "--tracks", "truth")
    assert status == 1 and "lens is distorted" in captured.err


def test_an_image_of_the_wrong_size_is_named(tmp_path):
    _write_dataset(tmp_path, seconds=0.1, image_size=(12, 16))
    with pytest.raises(EvaluationError, match=r"\.png: image is 16x12, the camera's "
                                              r"sensor.yaml says 32x24"):
        evaluate_vio(tmp_path, VinsOptions())


def _eval_vio(capsys, *args):
    status = main(["eval", "vio", *map(str, args)])
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    return status, captured


def test_a_missing_folder_fails_in_one_line(tmp_path, capsys):
    status, captured = _eval_vio(capsys, tmp_path / "nowhere")
    assert (status, captured.err) == (1, f"eval vio: {tmp_path / 'nowhere'}: no such folder\n")


def test_a_folder_without_a_camera_is_named(tmp_path, capsys):
    status, captured = _eval_vio(capsys, tmp_path)
    assert status == 1
    assert captured.err == f"eval vio: {tmp_path / 'mav0' / 'cam0' / 'data.csv'}: no such file\n"


def test_a_garbage_csv_is_named_with_its_problem(tmp_path, capsys):
    _write_dataset(tmp_path, seconds=0.1)
    (tmp_path / "mav0" / "imu0" / "data.csv").write_text("#header\n12,garbage\n")
    status, captured = _eval_vio(capsys, tmp_path)
    assert status == 1
    assert captured.err.startswith("eval vio: ") and captured.err.count("\n") == 1
    assert "imu0/data.csv: sample 1 has 2 columns, expected 7" in captured.err


@pytest.mark.parametrize("args, complaint", [
    (("--max-frames", "0"), "expected a positive integer"),
    ((), "the following arguments are required: DATASET"),
])
def test_bad_arguments_exit_2(capsys, args, complaint):
    status, captured = _eval_vio(capsys, *args)
    assert status == 2 and complaint in captured.err


def test_eval_has_help_and_wants_an_action(capsys):
    assert main(["eval", "vio", "--help"]) == 0
    assert "--max-frames N" in capsys.readouterr().out
    assert main(["eval"]) == 2
    assert capsys.readouterr().err.startswith("usage: companion eval")


@pytest.fixture(scope="module")
def simulated(record_flight):
    return record_flight("mine", 8.0)


def test_a_trajectory_too_large_by_three_percent_reports_its_scale(tmp_path):
    _write_dataset(tmp_path)
    data = read_vio_dataset(tmp_path)
    trace = _known_trace(data, 81)
    trace.positions = [None if p is None else 1.03 * np.asarray(p) for p in trace.positions]
    result = score_vio(trace, data)
    assert result["scale"] == pytest.approx(1.03, rel=1e-6)
    assert result["scale_error"] == pytest.approx(1.0 - 1.0 / 1.03, rel=1e-6)
    assert result["ate_rmse_m"] > 1e-3


def test_the_vins_on_a_simulated_flight_reports_every_metric(simulated, capsys):
    status, captured = _eval_vio(capsys, simulated, "--json")
    assert status == 0, captured.err
    result = json.loads(captured.out)
    numbers = ("ate_rmse_m", "distance_m", "ate_over_distance", "scale_error", "scale",
               "depth_rel_err_median", "frontend_ms_median", "backend_ms_median",
               "backend_ms_p95", "correction_m_median", "correction_m_max",
               "nees_pose_mean", "nees_pose_median", "nees_velocity_mean",
               "nees_velocity_median", "track_error_px_median", "track_error_px_p90")
    assert set(result) >= {"dataset", "frames", "keyframes", "depth_points", "resets",
                           "health", "init", "drag_fit", *numbers}
    assert result["frames"] == 161 and 0 < result["keyframes"] <= 161
    assert all(isinstance(result[key], float) and result[key] >= 0.0 for key in numbers)
    assert sum(result["health"].values()) == 161
    assert result["nees_keyframes"] == result["keyframes"] - result["nees_refused"]
    assert result["depth_points"] > 0 and result["resets"] >= len(result["rebuilds"])
    assert result["init"]["gravity_err_deg"] < 1.0
    # Lucas-Kanade on the rendered mine: sub-pixel, and drifting as a track ages
    assert result["track_error_px_median"] < 1.0
    by_age = [b["median_px"] for b in result["track_error_by_age"]]
    assert None not in by_age and by_age[0] < by_age[-1]
    assert result["track_error_reference"] == "camera truth"
    # reported with the rest (what it measures is tests/test_eval_tracks.py's)
    by_texture = result["track_error_by_texture"]
    assert len(by_texture["bins"]) == 5 and isinstance(by_texture["spearman"], float)


@pytest.fixture(scope="module")
def realistic(tmp_path_factory):
    """5 s of the realistic mine (seed 0): 2 s standing, then the climb."""
    from drivers.camera.options import CameraOptions
    from drivers.sim.imu import ImuOptions
    from drivers.sim.options import SimOptions
    from drivers.sim.quadrotor import VehicleOptions
    from drivers.sim.record import record_dataset
    from drivers.sim.render import RenderError
    root = tmp_path_factory.mktemp("realistic_mine")
    try:
        record_dataset(root, SimOptions(world="mine", seed=0, profile="realistic"),
                       CameraOptions(), VehicleOptions(), ImuOptions(), duration=5.0)
    except RenderError as error:
        pytest.skip(f"EGL/OpenGL unavailable here: {error}")
    return root


def test_a_realistic_cameras_tracks_are_measured_through_its_truth(realistic):
    """Seen through the calibration, a track's error takes in the mounting's hidden 0.5 deg
    and the stamps' offset, and grows as the track moves in the image; through the camera's
    truth it is the tracker's alone (measured: 0.36 against 0.73 px past 20 frames; through
    the true mounting at the stamps, 0.68 px)."""
    data = read_vio_dataset(realistic)
    runs = {name: run_vins(dataset, VinsOptions(), consistency=False).track_errors
            for name, dataset in (("truth", data),
                                  ("calibration", dataclasses.replace(data, camera_truth=None)))}
    assert runs["truth"]["track_error_reference"] == "camera truth"
    assert runs["calibration"]["track_error_reference"] == "calibration"
    oldest = {name: run["track_error_by_age"][-1] for name, run in runs.items()}
    assert oldest["truth"]["observations"] == oldest["calibration"]["observations"] > 1000
    assert oldest["truth"]["median_px"] < 0.7 * oldest["calibration"]["median_px"]
    assert oldest["truth"]["median_px"] < 0.5  # the stamps' offset taken out too
    assert runs["truth"]["track_error_px_median"] < runs["calibration"]["track_error_px_median"]


def test_without_consistency_the_same_run_is_scored_without_the_nees(simulated):
    """The acceptance runs skip the NEES's marginal covariances; nothing else may change."""
    full = evaluate_vio(simulated, VinsOptions(), max_frames=100)
    quick = evaluate_vio(simulated, VinsOptions(), max_frames=100, consistency=False)
    nees = {key for key in full if key.startswith("nees_")}
    timing = {key for key in full if key.endswith(("_ms_median", "_ms_p95"))}
    assert {k: v for k, v in quick.items() if k not in nees | timing} == \
        {k: v for k, v in full.items() if k not in nees | timing}
    assert quick["nees_keyframes"] == 0 and quick["nees_pose_median"] is None
    assert full["nees_keyframes"] > 0


def test_the_bound_solves_the_smoothers_own_factors_under_the_starts_gauge_alone(simulated):
    """The batches take every factor the smoother was given but the gauge hold's priors (each
    held a keyframe at its estimate: several would pin distances, so the scale), and the
    causal batch at the last keyframe is the whole-flight batch there: the same factors."""
    log = FactorLog()
    trace = run_vins(read_vio_dataset(simulated), VinsOptions(), consistency=False,
                     factor_log=log)
    assert trace.resets == 0
    priors = [f for _, f in log.kept() if isinstance(f, gtsam.PriorFactorPose3)]
    held = [f for i, f in enumerate(log.factors)
            if i in log.removed and isinstance(f, gtsam.PriorFactorPose3)]
    assert len(priors) == 1 and len(held) >= 2  # the start's; the hold moved along the flight
    times = [t for t, _ in log.kept()]
    assert times == sorted(times)
    fixed_lag = {kf.t: kf.T_W_B[:3, 3] for kf in trace.keyframes}
    keyframes = batch_positions(log, fixed_lag, every=7)
    assert keyframes.t[-1] == max(fixed_lag) and len(keyframes.t) == len(keyframes.causal_batch)
    np.testing.assert_allclose(keyframes.causal_batch[-1], keyframes.whole_flight_batch[-1],
                               atol=1e-3)
    np.testing.assert_array_equal(keyframes.fixed_lag[-1], fixed_lag[max(fixed_lag)])


def test_eval_vio_bound_reports_the_smoother_beside_both_batches(simulated, capsys):
    status, captured = _eval_vio(capsys, simulated, "--bound")
    assert status == 0, captured.err
    line = next(line for line in captured.out.splitlines() if "what the factors allow" in line)
    assert all(name in line for name in ("the smoother", "causal batch", "whole-flight batch"))
    status, captured = _eval_vio(capsys, simulated, "--bound", "--json")
    bound = json.loads(captured.out)["bound"]
    assert bound["keyframes"] >= 3
    for name in ("fixed_lag", "causal_batch", "whole_flight_batch"):
        assert 0.0 <= bound[name]["ate_over_distance"] < 0.05
        assert abs(bound[name]["scale"] - 1.0) < 0.05


def test_a_path_too_straight_to_align_is_not_bounded_and_says_why(simulated, capsys):
    """The first 5 s are the still start and the climb: keyframes on one line."""
    status, captured = _eval_vio(capsys, simulated, "--bound", "--max-frames", "100", "--json")
    assert status == 0, captured.err
    assert json.loads(captured.out)["bound"]["note"].startswith("not bounded on ")


def test_truth_tracks_take_the_trackers_error_out_of_the_same_flight(simulated, capsys):
    """The same images and IMU, the tracker's tracks with every pixel the truth's: no track
    error left, on as many frames, and an estimate at least as close to the truth."""
    runs = {}
    for tracks in ("tracker", "truth"):
        status, captured = _eval_vio(capsys, simulated, "--json", "--tracks", tracks)
        assert status == 0, captured.err
        runs[tracks] = json.loads(captured.out)
    tracker, truth = runs["tracker"], runs["truth"]
    assert truth["frames"] == tracker["frames"] == 161
    assert tracker["track_error_px_median"] > 0.01
    assert truth["track_error_px_median"] < 1e-3 and truth["track_error_px_p90"] < 1e-3
    assert truth["depth_rel_err_median"] < tracker["depth_rel_err_median"]
    assert truth["ate_over_distance"] < 0.01


def test_early_and_late_error_tracks_each_keep_a_part_of_the_trackers_error(simulated, capsys):
    """The same flight on the truth with the tracker's error of each track's first frames
    only, and with only what it gathers after them: young tracks are the tracker's with
    early-error and exact with late-error; early-error stops the error growing (its tail a
    fraction of the tracker's), late-error takes out what the old tracks gathered in their
    first frames."""
    runs = {}
    for tracks in ("tracker", "early-error", "late-error"):
        status, captured = _eval_vio(capsys, simulated, "--json", "--tracks", tracks)
        assert status == 0, captured.err
        runs[tracks] = json.loads(captured.out)
    tracker, early, late = runs["tracker"], runs["early-error"], runs["late-error"]
    assert early["frames"] == late["frames"] == tracker["frames"]
    assert 0.01 < early["track_error_px_p90"] < 0.5 * tracker["track_error_px_p90"]
    assert late["track_error_px_median"] > 0.01
    young = {name: run["track_error_by_age"][0] for name, run in runs.items()}
    old = {name: run["track_error_by_age"][-1] for name, run in runs.items()}
    assert {o["ages"] for o in young.values()} == {"2-4"}
    assert {o["ages"] for o in old.values()} == {"20+"}
    assert young["late-error"]["median_px"] < 1e-6
    assert young["early-error"]["median_px"] == pytest.approx(young["tracker"]["median_px"],
                                                              rel=0.2)
    assert old["late-error"]["median_px"] < old["tracker"]["median_px"]


@pytest.mark.parametrize("problem, complaint", [
    ("distorted lens", "lens is distorted: record the ideal profile"),
    ("no depth0", "truth tracks need the true depth of every frame"),
])
def test_truth_tracks_on_a_recording_they_cannot_be_projected_into_fail_in_one_line(
        tmp_path, capsys, problem, complaint):
    _write_dataset(tmp_path, distortion=(-0.28, 0.07, 0.0, 0.0) if problem == "distorted lens"
                   else (0.0, 0.0, 0.0, 0.0))
    if problem == "no depth0":
        shutil.rmtree(tmp_path / "mav0" / "depth0")
    status, captured = _eval_vio(capsys, tmp_path, "--tracks", "truth")
    assert status == 1 and complaint in captured.err
    assert len(captured.err.strip().splitlines()) == 1


def test_a_scale_that_grows_through_the_flight_shows_window_by_window(tmp_path):
    """A trajectory whose size grows from the truth's at the start to 6 % over it at the end
    (as the mine's shrinks) scores a scale that rises window by window."""
    _write_dataset(tmp_path, seconds=20.0)
    data = read_vio_dataset(tmp_path)
    trace = _known_trace(data, 401)
    known = [k for k, p in enumerate(trace.positions) if p is not None]
    start, end = trace.t[known[0]], trace.t[known[-1]]
    growth = lambda t: 1.0 + 0.06 * (t - start) / (end - start)  # noqa: E731
    origin = np.asarray(trace.positions[known[0]])
    trace.positions = [None if p is None else origin + growth(t) * (np.asarray(p) - origin)
                       for t, p in zip(trace.t, trace.positions)]
    windows = score_vio(trace, data)["scale_by_time"]
    assert len(windows) >= 2
    scales = [w["scale"] for w in windows]
    assert scales == sorted(scales) and scales[0] < 1.03 < scales[-1]
