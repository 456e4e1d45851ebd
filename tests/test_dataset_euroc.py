"""The EuRoC/ASL reader and writer: our recordings read back exactly, and so does the real one."""

from pathlib import Path

import numpy as np
import pytest

from autonomy.geometry import R_BODY_CAMERA, PinholeCamera, make_pose, so3_exp
from autonomy.vins.preintegration import ImuNoise
from drivers.dataset.euroc import (
    DatasetError, EurocWriter, depth_to_millimetres, read_camera, read_camera_truth,
    read_depth_png, read_groundtruth, read_imu, read_imu_noise,
)

EUROC = Path(__file__).resolve().parents[2] / "shared" / "data" / "euroc_v1_01"
NOISE = {"rate_hz": 200.0, "gyroscope_noise_density": 1e-4, "gyroscope_random_walk": 1e-5,
         "accelerometer_noise_density": 1e-3, "accelerometer_random_walk": 1e-4}


def test_depth_millimetres_mark_unknown_and_out_of_range_as_zero():
    depth = np.array([[np.nan, -1.0, 0.0, 0.0004], [0.0006, 1.2345, 65.535, 65.6]])
    assert depth_to_millimetres(depth).tolist() == [[0, 0, 0, 0], [1, 1234, 65535, 0]]


def _frames_with_truth(root: Path, truth: bool = True) -> np.ndarray:
    """Three frames stamped 15 ms after their exposure, with the camera's truth (a mounting
    1 degree off the configured one) when ``truth``. Returns the true mounting."""
    camera = PinholeCamera.from_hfov(64, 48, 1.5)
    true_T_B_C = make_pose(R_BODY_CAMERA @ so3_exp(np.radians([0.0, 1.0, 0.0])), [0.1, 0, 0])
    with EurocWriter(root, camera, make_pose(R_BODY_CAMERA, [0.1, 0, 0]), 20.0, NOISE) as writer:
        if truth:
            writer.add_camera_truth(true_T_B_C)
        for k in range(3):
            writer.add_frame(50_000_000 * k + 15_000_000, np.zeros((48, 64, 3), np.uint8),
                             np.ones((48, 64), np.float32), 50_000_000 * k if truth else None)
    return true_T_B_C


def test_a_simulators_camera_truth_reads_back_beside_the_calibration(tmp_path):
    true_T_B_C = _frames_with_truth(tmp_path)
    stream = read_camera(tmp_path)
    truth = read_camera_truth(tmp_path, stream)
    assert truth.exposed_ns.tolist() == [0, 50_000_000, 100_000_000]
    np.testing.assert_allclose(truth.T_B_C, true_T_B_C, atol=1e-12)
    np.testing.assert_allclose(stream.T_B_C, make_pose(R_BODY_CAMERA, [0.1, 0, 0]), atol=1e-12)


def test_a_recording_without_the_cameras_truth_has_none(tmp_path):
    _frames_with_truth(tmp_path, truth=False)
    assert read_camera_truth(tmp_path, read_camera(tmp_path)) is None


def test_half_a_camera_truth_or_one_of_other_stamps_is_refused(tmp_path):
    _frames_with_truth(tmp_path / "half")
    (tmp_path / "half" / "mav0" / "cam0" / "truth.yaml").unlink()
    with pytest.raises(DatasetError, match="truth.yaml: no such file"):
        read_camera_truth(tmp_path / "half", read_camera(tmp_path / "half"))
    _frames_with_truth(tmp_path / "other")
    table = tmp_path / "other" / "mav0" / "cam0" / "truth.csv"
    table.write_text(table.read_text().replace("115000000,", "116000000,"))
    with pytest.raises(DatasetError, match=r"its stamps are not those of .*frame 3 differs"):
        read_camera_truth(tmp_path / "other", read_camera(tmp_path / "other"))
    _frames_with_truth(tmp_path / "table")
    (tmp_path / "table" / "mav0" / "cam0" / "truth.csv").unlink()
    with pytest.raises(DatasetError, match="truth.csv: no such file"):
        read_camera_truth(tmp_path / "table", read_camera(tmp_path / "table"))


@pytest.mark.parametrize("exposure", ["1.5e7", "99999999999999999999", "-"])
def test_an_exposure_time_that_is_no_timestamp_is_refused(tmp_path, exposure):
    _frames_with_truth(tmp_path)
    table = tmp_path / "mav0" / "cam0" / "truth.csv"
    table.write_text(table.read_text().replace(",50000000", f",{exposure}"))
    with pytest.raises(DatasetError, match=r"truth.csv: (bad timestamp|a timestamp beyond).* "
                                           r"\(the exposures, column 2\)"):
        read_camera_truth(tmp_path, read_camera(tmp_path))


def test_written_dataset_reads_back(tmp_path):
    camera = PinholeCamera.from_hfov(64, 48, 1.5)
    T_B_C = make_pose(R_BODY_CAMERA, np.array([0.1, 0.0, 0.05]))
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 20.0, (48, 64)).astype(np.float32)
    depth[0, 0] = np.nan
    rgb = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    with EurocWriter(tmp_path, camera, T_B_C, 20.0, NOISE) as writer:
        for k in range(3):
            t_ns = 5_000_000 * k
            writer.add_imu(t_ns, [0.1, 0.2, 0.3 + k], [0.0, 0.0, 9.8])
            writer.add_groundtruth(t_ns, [k, 0, 1], [1, 0, 0, 0], [1, 0, 0], [0] * 3, [0] * 3)
        writer.add_frame(0, rgb, depth)

    imu, truth, stream = read_imu(tmp_path), read_groundtruth(tmp_path), read_camera(tmp_path)
    assert imu.t_ns.tolist() == [0, 5_000_000, 10_000_000]
    assert np.allclose(imu.gyro[2], [0.1, 0.2, 2.3]) and np.allclose(imu.accel[0], [0, 0, 9.8])
    assert np.allclose(truth.position[:, 0], [0, 1, 2]) and np.allclose(truth.q_W_B[1], [1, 0, 0, 0])
    read_back = stream.camera
    assert (read_back.width, read_back.height) == (64, 48)
    assert [read_back.fx, read_back.fy, read_back.cx, read_back.cy] == pytest.approx(
        [camera.fx, camera.fy, camera.cx, camera.cy], rel=1e-11)
    assert np.allclose(stream.T_B_C, T_B_C) and stream.rate_hz == 20.0
    depth_back = read_depth_png(read_camera(tmp_path, "depth0").paths[0])
    assert np.isnan(depth_back[0, 0])
    assert np.allclose(depth_back[1:], depth[1:], atol=0.0005)


def test_reading_the_real_euroc_recording():
    if not EUROC.is_dir():
        pytest.skip(f"real EuRoC data not found at {EUROC}")
    imu, truth, cam = read_imu(EUROC), read_groundtruth(EUROC), read_camera(EUROC)
    assert len(imu.t_ns) == 29120 and np.median(np.diff(imu.t_ns)) == pytest.approx(5e6, rel=1e-3)
    # At rest on the ground the accelerometer reads gravity's magnitude.
    assert np.linalg.norm(imu.accel[:100].mean(axis=0)) == pytest.approx(9.81, abs=0.1)
    assert np.allclose(np.linalg.norm(truth.q_W_B, axis=1), 1.0, atol=1e-4)
    assert cam.camera.width == 752 and cam.distortion[0] == pytest.approx(-0.28340811)
    assert all(path.is_file() for path in cam.paths)


def test_malformed_files_are_named_with_the_problem(tmp_path):
    (tmp_path / "mav0" / "imu0").mkdir(parents=True)
    csv = tmp_path / "mav0" / "imu0" / "data.csv"
    csv.write_text("#header\n0,1,2,3,4,5,6\n5,1,2,3\n")
    with pytest.raises(DatasetError, match=r"data.csv: sample 2 has 4 columns"):
        read_imu(tmp_path)
    csv.write_text("#header\n5,1,2,3,4,5,6\n5,1,2,3,4,5,6\n")
    with pytest.raises(DatasetError, match="not strictly increasing"):
        read_imu(tmp_path)
    with pytest.raises(DatasetError, match="no such file"):
        read_groundtruth(tmp_path)
    bad_png = tmp_path / "depth.png"
    bad_png.write_bytes(b"not a png")
    with pytest.raises(DatasetError, match="not a readable image"):
        read_depth_png(bad_png)


def test_values_that_are_not_numbers_or_not_in_order_are_named(tmp_path):
    """What the fuzzer found the reader let through or choked on (fuzz/regressions/
    euroc_reader/): each is a DatasetError naming the file."""
    imu = tmp_path / "mav0" / "imu0" / "data.csv"
    imu.parent.mkdir(parents=True)
    for text, problem in [("1,nan,0,0,0,0,0\n", "sample 1 holds a value that is not a finite"),
                          ("99999999999999999999,0,0,0,0,0,0\n", "beyond 64-bit nanoseconds"),
                          ("1,0,0,0,0,0,0\xb5\n", r"not ASCII text \(byte 13\)")]:
        imu.write_bytes(text.encode("latin-1"))
        with pytest.raises(DatasetError, match=problem):
            read_imu(tmp_path)
    with EurocWriter(tmp_path, PinholeCamera.from_hfov(64, 48, 1.5), np.eye(4), 20.0, NOISE):
        pass
    frames = tmp_path / "mav0" / "cam0" / "data.csv"
    for text, problem in [("", "no frames"), ("5,a.png\n5,b.png\n", "not strictly increasing"),
                          ("5\n", "frame 1 has 1 columns, expected 2")]:
        frames.write_text(text)
        with pytest.raises(DatasetError, match=problem):
            read_camera(tmp_path)


def test_a_camera_yaml_that_says_too_little_is_named(tmp_path):
    with EurocWriter(tmp_path, PinholeCamera.from_hfov(64, 48, 1.5), np.eye(4), 20.0, NOISE):
        pass
    (tmp_path / "mav0" / "cam0" / "data.csv").write_text("5,a.png\n")
    yaml = tmp_path / "mav0" / "cam0" / "sensor.yaml"
    text = yaml.read_text()
    for old, new, problem in [("rate_hz: 20", "", "missing rate_hz"),
                              ("rate_hz: 20", "rate_hz: 0", "rate_hz must be a positive"),
                              ("resolution: [64, 48]", "resolution: [64]", "resolution has 1"),
                              ("resolution: [64, 48]", "resolution: [64.5, 48]", "whole pixels"),
                              ("T_BS:", "T_SB:", "missing T_BS"),
                              ("data: [1, 0,", "data: [2, 0,", "T_BS is not a rigid transform"),
                              ("data: [1, 0,", "data: [-1, 0,",  # a reflection
                               "T_BS is not a rigid transform"),
                              ("0, 0, 0, 1]", "0, 0, 0.5, 1]", "T_BS is not a rigid transform"),
                              ("intrinsics: [", "intrinsics: [.inf, ", "intrinsics has 5")]:
        yaml.write_text(text.replace(old, new))
        with pytest.raises(DatasetError, match=problem):
            read_camera(tmp_path)
    yaml.write_text("- 1\n")
    with pytest.raises(DatasetError, match="sensor.yaml: not a YAML map of keys"):
        read_camera(tmp_path)


def test_a_mounting_written_to_four_decimals_is_read(tmp_path):
    """A rotation copied by hand from a calibration report, to four decimals, is a mounting
    (within ``ROTATION_TOLERANCE``), not refused as a sheared one."""
    R = R_BODY_CAMERA @ so3_exp(np.radians([0.3, -0.5, 0.2]))
    T = np.eye(4)
    T[:3, :3] = np.round(R, 4)
    assert not np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-6)  # not exact
    with EurocWriter(tmp_path, PinholeCamera.from_hfov(64, 48, 1.5), T, 20.0, NOISE):
        pass
    (tmp_path / "mav0" / "cam0" / "data.csv").write_text("5,a.png\n")
    read = read_camera(tmp_path).T_B_C
    # passed on as the nearest rotation, within the rounding of what was written
    assert np.allclose(read[:3, :3].T @ read[:3, :3], np.eye(3), atol=1e-12)
    assert np.abs(read - T).max() < 2e-4


def test_imu_noise_reads_back_and_names_a_missing_key(tmp_path):
    with EurocWriter(tmp_path, PinholeCamera.from_hfov(64, 48, 1.5), np.eye(4), 20.0, NOISE):
        pass
    assert read_imu_noise(tmp_path) == ImuNoise(gyro_noise_density=1e-4, gyro_random_walk=1e-5,
                                                accel_noise_density=1e-3, accel_random_walk=1e-4)
    if EUROC.is_dir():  # the real file, with its comments, reads as the documented defaults
        assert read_imu_noise(EUROC) == ImuNoise()
    yaml = tmp_path / "mav0" / "imu0" / "sensor.yaml"
    text = yaml.read_text()
    yaml.write_text(text.replace("gyroscope_random_walk", "gyro_walk"))
    with pytest.raises(DatasetError, match="sensor.yaml: missing gyroscope_random_walk"):
        read_imu_noise(tmp_path)
    yaml.write_text(text.replace("accelerometer_random_walk: 0.0001",
                                 "accelerometer_random_walk: -1"))
    with pytest.raises(DatasetError, match="accel_random_walk: must be >= 0, got -1.0"):
        read_imu_noise(tmp_path)
    yaml.write_text("%YAML:1.0\n[unclosed: {\n")
    with pytest.raises(DatasetError, match="sensor.yaml"):
        read_imu_noise(tmp_path)
    yaml.unlink()
    with pytest.raises(DatasetError, match="sensor.yaml: no such file"):
        read_imu_noise(tmp_path)
