"""The calibrations a flight learned, kept for the next flight: the camera-IMU time offset
(written only when the estimate moved) and the gyro's yaw response (written only when it was
estimated), read back for the same camera and mode only; a bad file is named and ignored (the
flight starts as configured)."""

import json
import logging
from datetime import datetime, timezone

import pytest

from autonomy.vins.gyro_alignment import GyroAlignmentEstimate
from autonomy.vins.time_offset import TimeOffset
from companion.config import load_config
from companion.flight.app import gyro_alignment_summary, time_offset_summary
from companion.launch.learned_calibration import (
    camera_identity, keep_learned, learned_alignment_path, learned_offset_path,
    start_from_learned,
)

NOW = datetime(2026, 11, 26, 12, 0, tzinfo=timezone.utc)


def _config(tmp_path, *overrides):
    return load_config("config/orin-d455.toml", [
        f"camera.learned_time_offset_file={tmp_path / 'offset.json'}",
        "camera.learned_gyro_alignment_file=", *overrides])


def _summary(seconds=0.0123, sigma=0.0004, estimating=True) -> dict:
    return {"vins_time_offset": time_offset_summary(TimeOffset(seconds, sigma, estimating))}


def test_an_offset_kept_after_a_flight_is_where_the_next_flight_starts(tmp_path):
    config = _config(tmp_path)
    assert config.vins.time_offset_s == 0.0
    [path] = keep_learned(config, _summary(), NOW)
    assert json.loads(path.read_text()) == {
        "format": 1, "camera": "realsense '' 640x480 at 30 Hz", "offset_s": 0.0123,
        "sigma_s": 0.0004, "saved": "2026-11-26T12:00:00+00:00"}
    assert not list(tmp_path.glob("*.partial"))
    assert start_from_learned(config).vins.time_offset_s == 0.0123


@pytest.mark.parametrize("summary", [
    _summary(sigma=None),  # the estimate never moved: nothing learned
    _summary(estimating=False),  # a fixed offset is the configuration's, not learned
    {},  # a flight that never got a VINS
])
def test_nothing_is_kept_unless_the_estimate_moved(tmp_path, summary):
    assert keep_learned(_config(tmp_path), summary, NOW) == []
    assert not (tmp_path / "offset.json").exists()


def test_offsets_are_not_kept_when_the_file_is_unset_or_the_offset_not_estimated(tmp_path):
    assert learned_offset_path(load_config("config/orin-d455.toml", [
        "camera.learned_time_offset_file="])) is None
    config = _config(tmp_path, "vins.estimate_time_offset=false")
    assert learned_offset_path(config) is None
    assert keep_learned(config, _summary(), NOW) == []


def test_another_camera_or_mode_starts_from_the_configuration(tmp_path, caplog):
    keep_learned(_config(tmp_path), _summary(), NOW)
    for other in ('realsense.serial="123456789"', "camera.rate_hz=15"):
        assert start_from_learned(_config(tmp_path, other)).vins.time_offset_s == 0.0
    assert "learned with another camera, realsense '' 640x480 at 30 Hz; this one is " \
           "realsense '123456789' 640x480 at 30 Hz" in caplog.text
    assert "this one is realsense '' 640x480 at 15 Hz" in caplog.text


def test_the_camera_is_named_by_its_driver_device_and_mode():
    oak = load_config("config/orin-oak.toml", [])
    assert camera_identity(oak) == f"oak '' CAM_B {oak.camera.width}x{oak.camera.height} at " \
                                   f"{oak.camera.rate_hz:g} Hz"
    assert camera_identity(load_config(None, ["camera.driver=v4l2"])).startswith(
        "v4l2 '/dev/video0' 640x480")


@pytest.mark.parametrize("content, complaint", [
    ("{not json", "not JSON"),
    ('[1, 2]', "not a format-1 file of learned calibration"),
    ('{"format": 2}', "not a format-1 file of learned calibration"),
    ('{"format": 1, "camera": "realsense \'\' 640x480 at 30 Hz", "offset_s": "12 ms"}',
     "offset_s is '12 ms', not a finite number"),
    ('{"format": 1, "camera": "realsense \'\' 640x480 at 30 Hz", "offset_s": NaN}',
     "offset_s is nan, not a finite number"),
    ('{"format": 1, "camera": "realsense \'\' 640x480 at 30 Hz", "offset_s": 0.2}',
     "time_offset_s"),  # beyond [vins] max_time_offset_s: the options refuse it
])
def test_a_bad_file_is_named_and_ignored(tmp_path, caplog, content, complaint):
    (tmp_path / "offset.json").write_text(content)
    config = _config(tmp_path)
    assert start_from_learned(config) is config
    assert f"ignoring the learned camera-IMU time offset in {tmp_path / 'offset.json'}" \
           in caplog.text and complaint in caplog.text


COLUMN = (-0.0185, 0.0036, -0.0028)


def _alignment_config(tmp_path, *overrides):
    return _config(tmp_path, f"camera.learned_gyro_alignment_file={tmp_path / 'gyro.json'}",
                   *overrides)


def _alignment_summary(pairs=670) -> dict:
    return {"vins_gyro_alignment": gyro_alignment_summary(
        GyroAlignmentEstimate(COLUMN, (0.0024, 0.0026, 0.0023) if pairs else None, pairs))}


def test_a_gyro_alignment_estimated_on_a_calibration_flight_corrects_every_later_flight(
        tmp_path):
    calibration = _alignment_config(tmp_path, "vins.estimate_gyro_alignment=true")
    [path] = keep_learned(calibration, _alignment_summary(), NOW)
    assert path == tmp_path / "gyro.json"
    assert json.loads(path.read_text()) == {
        "format": 1, "camera": "realsense '' 640x480 at 30 Hz", "gyro_alignment": list(COLUMN),
        "sigma": [0.0024, 0.0026, 0.0023], "pairs": 670, "saved": "2026-11-26T12:00:00+00:00"}
    later = _alignment_config(tmp_path)  # the estimate off: the learned column, fixed
    assert later.vins.gyro_alignment == (0.0, 0.0, 0.0)
    started = start_from_learned(later)
    assert started.vins.gyro_alignment == COLUMN and not started.vins.estimate_gyro_alignment
    assert started.vins.time_offset_s == later.vins.time_offset_s  # no offset file yet


def test_with_no_column_kept_yet_the_flight_estimates_it(tmp_path, caplog):
    caplog.set_level(logging.INFO)
    first = start_from_learned(_alignment_config(tmp_path))
    assert first.vins.estimate_gyro_alignment and first.vins.gyro_alignment == (0.0, 0.0, 0.0)
    assert f"no gyro yaw response kept for this camera ({tmp_path / 'gyro.json'})" in caplog.text
    # the estimate needs the time offset's frame pairs: without them the flight is as configured
    no_pairs = _alignment_config(tmp_path, "vins.estimate_time_offset=false")
    assert start_from_learned(no_pairs) is no_pairs


def test_a_column_the_flight_did_not_show_is_not_kept(tmp_path):
    config = _alignment_config(tmp_path, "vins.estimate_gyro_alignment=true")
    summary = {"vins_gyro_alignment": gyro_alignment_summary(
        GyroAlignmentEstimate(COLUMN, (0.0113, 0.0113, 0.0048), 40))}  # half the prior's: 0.007
    assert keep_learned(config, summary, NOW) == []
    assert not (tmp_path / "gyro.json").exists()


#: A whole misalignment by rows, its yaw column COLUMN's.
MATRIX = ((0.003, -0.021, COLUMN[0]), (0.010, 0.002, COLUMN[1]), (-0.027, 0.016, COLUMN[2]))


def _matrix_summary(largest_sigma: float) -> dict:
    sigma = ((0.003, 0.004, 0.0024), (0.004, 0.003, 0.0026), (0.005, largest_sigma, 0.0023))
    return {"vins_gyro_alignment": gyro_alignment_summary(GyroAlignmentEstimate(
        COLUMN, (0.0024, 0.0026, 0.0023), 1300, MATRIX, sigma))}


def test_a_whole_misalignment_the_flight_showed_is_kept_and_corrects_the_next_flight(tmp_path):
    calibration = _alignment_config(tmp_path, "vins.estimate_gyro_alignment=true",
                                    'vins.gyro_alignment_rates="all"')
    [path] = keep_learned(calibration, _matrix_summary(0.006), NOW)
    rows = [v for row in MATRIX for v in row]
    assert json.loads(path.read_text())["gyro_alignment"] == rows
    started = start_from_learned(_alignment_config(tmp_path))
    assert started.vins.gyro_alignment == tuple(rows)


def test_of_a_whole_misalignment_not_all_shown_the_yaw_column_is_kept(tmp_path):
    calibration = _alignment_config(tmp_path, "vins.estimate_gyro_alignment=true",
                                    'vins.gyro_alignment_rates="all"')
    keep_learned(calibration, _matrix_summary(0.009), NOW)  # over half the prior's 0.014
    assert start_from_learned(_alignment_config(tmp_path)).vins.gyro_alignment == COLUMN


def test_a_flight_keeps_both_calibrations_and_the_next_starts_from_both(tmp_path):
    config = _alignment_config(tmp_path, "vins.estimate_gyro_alignment=true")
    kept = keep_learned(config, {**_summary(), **_alignment_summary()}, NOW)
    assert kept == [tmp_path / "offset.json", tmp_path / "gyro.json"]
    started = start_from_learned(config)
    assert (started.vins.time_offset_s, started.vins.gyro_alignment) == (0.0123, COLUMN)


def test_a_gyro_alignment_given_not_estimated_is_not_written_back(tmp_path):
    config = _alignment_config(tmp_path, "vins.gyro_alignment=[0.01, 0.0, 0.0]")
    assert keep_learned(config, _alignment_summary(pairs=0), NOW) == []
    assert keep_learned(config, {"vins_gyro_alignment": None}, NOW) == []
    assert not (tmp_path / "gyro.json").exists()
    assert learned_alignment_path(load_config("config/orin-d455.toml", [
        "camera.learned_gyro_alignment_file="])) is None


@pytest.mark.parametrize("column, complaint", [
    ('"0.01"', "gyro_alignment is '0.01', not three or nine finite numbers"),
    ("[0.01, 0.02]", "gyro_alignment is [0.01, 0.02], not three or nine finite numbers"),
    ("[0.01, NaN, 0.0]", "not three or nine finite numbers"),
    ("[0.01, true, 0.0]", "not three or nine finite numbers"),
    ("[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]", "not three or nine finite numbers"),
    ("[0.9, 0.0, 0.0]", "gyro_alignment"),  # beyond what the options take
])
def test_a_bad_gyro_alignment_file_is_named_and_ignored(tmp_path, caplog, column, complaint):
    (tmp_path / "gyro.json").write_text(
        '{"format": 1, "camera": "realsense \'\' 640x480 at 30 Hz", "gyro_alignment": '
        f'{column}}}')
    config = _alignment_config(tmp_path, "vins.estimate_time_offset=false")
    assert start_from_learned(config) is config
    assert f"ignoring the learned gyro alignment in {tmp_path / 'gyro.json'}" in caplog.text
    assert complaint in caplog.text


def test_an_ignored_gyro_alignment_file_is_learned_again_and_replaced(tmp_path, caplog):
    (tmp_path / "gyro.json").write_text("{not json")
    started = start_from_learned(_alignment_config(tmp_path))
    assert "ignoring the learned gyro alignment" in caplog.text
    assert started.vins.estimate_gyro_alignment and started.vins.gyro_alignment == (0.0, 0.0, 0.0)
    assert keep_learned(started, _alignment_summary(), NOW) == [tmp_path / "gyro.json"]
    assert start_from_learned(_alignment_config(tmp_path)).vins.gyro_alignment == COLUMN


def test_a_file_that_cannot_be_written_is_named_and_the_flight_goes_on(tmp_path, caplog):
    (tmp_path / "gyro.json").mkdir()  # ignored as unreadable, and not replaceable
    started = start_from_learned(_alignment_config(tmp_path))
    assert keep_learned(started, _alignment_summary(), NOW) == []
    assert f"could not keep the learned calibration in {tmp_path / 'gyro.json'}" in caplog.text
    assert not list(tmp_path.glob("*.partial"))


def test_a_gyro_alignment_learned_with_another_camera_is_not_used(tmp_path, caplog):
    keep_learned(_alignment_config(tmp_path, "vins.estimate_gyro_alignment=true"),
                 _alignment_summary(), NOW)
    other = _alignment_config(tmp_path, 'realsense.serial="123456789"')
    started = start_from_learned(other)
    assert started.vins.gyro_alignment == (0.0, 0.0, 0.0)
    assert "learned with another camera" in caplog.text
    # the new camera calibrates itself: its flight estimates the column, and keeps it
    assert started.vins.estimate_gyro_alignment
    keep_learned(started, _alignment_summary(), NOW)
    record = json.loads((tmp_path / "gyro.json").read_text())
    assert record["camera"] == camera_identity(other)
