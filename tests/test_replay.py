"""``companion replay`` (issue 22): a recorded simulated flight through the stages again.

One lockstep dome flight, recorded with a lossless camera, is replayed with its own config
and with another rescaling method. With its own config the replay must be the flight: the
VINS frame for frame, the depth's accuracy (the true depth is recorded exact, so the synthetic
network distorts what it did; the recorded metric depth is millimetres, which the score
rounds), and the planner's decisions;
with the exponential fit, which ``companion eval rescale`` ranks far below the default
(docs/results.md: dome AbsRel 0.175 against 0.112 with VINS anchors), the depth must be worse.
The same recording's true poses give ``companion log vins``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
import types

import cv2
import mcap.writer
import numpy as np
import pytest

from companion import cli
from companion.config import load_config
from autonomy.geometry import quat_to_rot, so3_exp, yaw_of
from companion.launch import simulated
from drivers.sim.faults import Fault
from drivers.sim.host import SimMission

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """The recording of 12 s of the dome's first pair, lockstep, PNG camera, the go 2 s into
    the wait for it (the VINS's zero-velocity prior on the ground, which the replay must give
    where the flight did), the camera's time offset estimated and the offset swing on, so the
    flight swings for it before navigating (docs/flight.md, CALIBRATING). Lockstep runs faster
    than real time, so the writer may fall behind on a busy machine: a queue as long as the
    flight keeps every image (docs/recording.md, "Drops"). The mock's step take-off: with PX4's
    smoothed climb (1.5 s longer to 1.5 m) the 12 s held 11 degrees of the swing's yaw, where
    ``test_record_along_timed_flies_the_flights_own_motion_again`` needs a turn of 15."""
    directory = tmp_path_factory.mktemp("recordings")
    config = load_config(None, [f"recorder.directory={directory}", "flight.mission_timeout_s=12",
                                "recorder.camera_format=png", "recorder.camera_queue=1000",
                                "vins.estimate_time_offset=true", "flight.offset_swing_deg=10",
                                "px4.smooth_takeoff=false"])
    summary = simulated.run(config, simulated.SimMission(world="dome", go_after_s=2.0),
                            record=True)
    assert summary["recording"]["error"] is None and not summary["recording"]["dropped"]
    assert summary["vins_still_keyframes"] > 0
    return summary


def replay(path, *options) -> dict:
    """``companion replay PATH --json OPTIONS``'s report."""
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert cli.main(["replay", path, "--json", *options]) == 0
    return json.loads(printed.getvalue())


@pytest.fixture(scope="module")
def own(recording, tmp_path_factory):
    """The replay with the flight's own config (and a top view), replayed once for every
    test that compares with it."""
    top_view = tmp_path_factory.mktemp("replay") / "replay.png"
    return replay(recording["recording"]["path"], "--plot", str(top_view)), top_view


def test_a_replay_with_the_flights_own_config_is_the_flight(recording, own):
    report, top_view = own
    assert report["plot"] == str(top_view) and top_view.stat().st_size > 1000
    # every frame the flight's VINS finished (the last one taken may have come as it ended)
    assert recording["frames"] - 1 <= report["frames"] <= recording["frames"]
    assert report["vins_same_frames"] == report["frames"]
    assert report["lossy_frames"] == 0  # PNG: the frames the flight tracked
    assert report["frames_with_depth"]["replayed"] == report["frames_with_depth"]["recorded"]
    # measured 0.0002 apart (0.0003 with the true depth in millimetres, per frame up to 0.08)
    assert report["abs_rel"]["replayed"] == pytest.approx(report["abs_rel"]["recorded"],
                                                          abs=0.001)
    assert report["planner_rounds"] > 50 and report["planner_agreement"] >= 0.98


def test_a_worse_rescaling_method_replays_to_worse_depth(recording, own):
    """Over the flight's first 18 s (``--until``: the navigation up to its mission timeout),
    against the flight's own depth over the same frames, which the own-config replay is."""
    own_report, _ = own
    exponential = replay(recording["recording"]["path"], "--until", "18",
                         "--set", "rescale.method=exponential")
    assert exponential["vins_same_frames"] == exponential["frames"]  # only the depth changed
    assert exponential["abs_rel"]["replayed"] > exponential["abs_rel"]["recorded"] + 0.02
    # the span and the recorded side both cut at 18 s: 20 frames a second from the start
    assert exponential["frames"] == pytest.approx(18 * 20, abs=2)
    assert 0 < exponential["frames_with_depth"]["recorded"] \
        < own_report["frames_with_depth"]["recorded"]
    assert exponential["frames_with_depth"]["replayed"] == \
        exponential["frames_with_depth"]["recorded"]
    assert exponential["failsafes"]["recorded"] == []  # the timeout came at 18.2 s


def test_a_config_that_starves_the_planner_of_depth_replays_to_its_failsafe(recording, own):
    """The flight's own failsafe was its 12 s mission timeout; with fits that need more
    anchors than a frame ever has and no affine fallback, the replay has no metric depth, and
    the depth rule fires once the flight is guarded."""
    own_report, _ = own
    starved = replay(recording["recording"]["path"], "--until", "10",  # guarded from 6.2 s
                     "--set", "rescale.min_anchors=5000", "--set", "depth.fallback_min_anchors=0")
    recorded = [f["reason"] for f in own_report["failsafes"]["recorded"]]
    assert recording["failsafes"] == ["mission timeout"]
    assert recorded == ["failsafe: mission timeout"]  # the transition into failsafe_stop
    assert own_report["failsafes"]["replayed_first"] is None
    assert starved["frames_with_depth"]["replayed"] == 0
    assert starved["failsafes"]["replayed_first"]["reason"].startswith("no metric depth")


def test_the_replay_scores_its_vins_where_navigation_ended_as_the_flight_did(recording, own):
    """With the flight's own config the replayed VINS is the flight's, so both end the same
    distance off, and that is the distance the flight's summary scored (its estimate at the
    clock's time when navigation ended, the frame's within a few centimetres)."""
    report, _ = own
    scored = report["vins_error"]
    assert scored["at"] == "navigation's end"
    assert scored["replayed"] == scored["recorded"]
    assert scored["recorded"]["error_m"] == pytest.approx(recording["position_error_m"],
                                                          abs=0.03)
    assert scored["recorded"]["split"]["scale"] == pytest.approx(
        recording["position_error_split"]["scale"], abs=0.01)


def test_a_replay_of_the_vins_alone_scores_it_alike_and_takes_its_options(recording, own):
    """``--vins-only``: the own config's VINS ends where the full replay's did, with no depth
    or plans made; a VINS option (the feature noise trebled) replays to another VINS, scored
    against the same recorded one."""
    own_report, _ = own
    alone = replay(recording["recording"]["path"], "--vins-only")
    assert alone["stages"] == ["vins"] and own_report["stages"] == ["vins", "depth", "planner"]
    assert alone["vins_error"] == own_report["vins_error"]
    assert alone["vins_same_frames"] == alone["frames"] == own_report["frames"]
    assert alone["planner_rounds"] == 0 and alone["frames_with_depth"]["replayed"] == 0
    assert set(alone["timings_ms"]) == {"vins"}
    noisier = replay(recording["recording"]["path"], "--vins-only", "--set",
                     "vins.pixel_sigma=3.0")
    assert noisier["vins_same_frames"] < noisier["frames"]
    assert noisier["vins_error"]["recorded"] == own_report["vins_error"]["recorded"]
    assert noisier["vins_error"]["replayed"]["error_m"] != \
        own_report["vins_error"]["replayed"]["error_m"]


def test_the_table_gives_the_vins_error_and_leaves_out_the_stages_not_replayed(own):
    from companion.cli.replay import format_report

    report, _ = own
    error = report["vins_error"]["recorded"]
    line = (f"  VINS error          at navigation's end ({report['vins_error']['t']:.1f} s): "
            f"recorded {error['error_m']:.2f} m (path scale {error['split']['scale']:.4f}), "
            f"replayed {error['error_m']:.2f} m (path scale {error['split']['scale']:.4f})")
    assert line in format_report(report).splitlines()
    assert "planner agreement" in format_report(report)
    alone = format_report({**report, "stages": ["vins"]})
    assert line in alone.splitlines() and "planner agreement" not in alone
    assert "VINS error          - (no truth" in format_report({**report, "vins_error": None})
    assert "lossy images" not in format_report(report)
    assert "  lossy images        5 stored as JPEG, not the frames the flight tracked" in \
        format_report({**report, "lossy_frames": 5})


def test_a_replay_counts_the_images_the_recorder_stored_lossy():
    """JPEG images are not the frames the flight tracked, so the report counts them; PNG ones
    are. The images are real encodings (as the recorder writes them), the message around them
    only what the decoder hands the replayer: its bytes and format."""
    from companion.recording.replay import VINS_ONLY, _Replayer

    replayer = _Replayer(load_config(None), None, VINS_ONLY)
    image = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    for t, image_format in enumerate(("jpeg", "png", "jpeg")):
        encoded = cv2.imencode("." + image_format, image)[1].tobytes()
        replayer._on_camera_image(t, types.SimpleNamespace(data=encoded, format=image_format))
    assert replayer.report.lossy_frames == 2 and len(replayer.frames) == 3


def test_a_replayed_vins_in_another_world_frame_is_tied_as_the_flight_tied_its_own():
    """The replayed VINS's world turned 30 degrees and moved (a config that started it
    otherwise): tied at the recorded tie's frame, its error is the recorded one's; its path
    4 % short shows as a 4 % short scale; without a tie there is nothing to score."""
    from autonomy.geometry import make_pose, rot_z
    from companion.recording.replay import _vins_at_end

    # frames at 1 and 2 ns: on the ground, where the flight tied the VINS, and at the end
    T_L_W = make_pose(rot_z(0.4), np.array([1.0, -2.0, 0.0]))
    recorded = {1: np.eye(4), 2: make_pose(rot_z(0.2), np.array([20.0, 5.0, 2.0]))}
    truth = {t: (T_L_W @ T)[:3, 3] for t, T in recorded.items()}
    truth[2] = truth[2] + np.array([0.3, 0.0, 0.0])  # the recorded VINS ends 0.3 m off
    T_V_W = make_pose(rot_z(np.radians(30.0)), np.array([4.0, 1.0, 0.0]))
    replayed = {t: T_V_W @ T for t, T in recorded.items()}
    scored = _vins_at_end({"recorded": recorded, "replayed": replayed}, truth, (1, T_L_W),
                          end_ns=None)
    assert scored["at"] == "the last frame"
    assert scored["recorded"]["error_m"] == pytest.approx(0.3)
    assert scored["replayed"]["error_m"] == pytest.approx(0.3)
    assert scored["replayed"]["split"] == pytest.approx(scored["recorded"]["split"], abs=2e-4)
    shorter = {1: replayed[1], 2: replayed[2].copy()}
    shorter[2][:3, 3] = replayed[1][:3, 3] + 0.96 * (replayed[2][:3, 3] - replayed[1][:3, 3])
    scale = _vins_at_end({"recorded": recorded, "replayed": shorter}, truth, (1, T_L_W),
                         end_ns=None)["replayed"]["split"]["scale"]
    assert scale == pytest.approx(0.96 * scored["recorded"]["split"]["scale"], abs=2e-4)
    assert _vins_at_end({"recorded": recorded, "replayed": replayed}, truth, None, None) is None


def test_record_along_flies_the_recorded_flights_own_path(recording, tmp_path):
    """``sim record --along``: the flight's world and seed, from where it stood, then along
    the path it truly flew (within the follower's tracking of a smoothed copy)."""
    from drivers.dataset.euroc import read_groundtruth

    out = tmp_path / "along"
    assert cli.main(["sim", "record", "--along", recording["recording"]["path"], "--duration",
                     "9", "--set", "camera.width=160", "--set", "camera.height=120",
                     "--out", str(out)]) == 0
    flown = np.array([sample["truth_position"] for sample in _log_vins(recording)])
    recorded = read_groundtruth(out).position
    np.testing.assert_allclose(recorded[0, :2], recording["start"][:2], atol=0.01)
    cruising = recorded[recorded[:, 2] > 1.0]
    assert len(cruising) > 200  # over a second of it, at 200 Hz
    nearest = np.min(np.linalg.norm(cruising[:, None, :2] - flown[None, :, :2], axis=2), axis=1)
    assert nearest.max() < 0.3


def test_record_along_timed_flies_the_flights_own_motion_again(recording, tmp_path):
    """``sim record --along --timed``: after standing as long as the flight stood on the
    floor, the recorder flies the flight's true motion from its lift-off (the climb, the
    offset swing's turns, the arcs) at the same pace, on the flight's clock (less the time
    before its first frame): at each moment the recorded vehicle is where the flight was,
    within the controller's tracking (a tenth of a second's lag at 2 m/s as it accelerates, a
    few centimetres at rest), and faces as it did."""
    from companion.recording.replay import flown_path
    from drivers.dataset.euroc import read_groundtruth

    out = tmp_path / "timed"
    assert cli.main(["sim", "record", "--along", recording["recording"]["path"], "--timed",
                     "--set", "camera.width=160", "--set", "camera.height=120",
                     "--out", str(out)]) == 0
    truth = flown_path(recording["recording"]["path"])  # every frame's true pose
    t, flown, yaw = truth.times, truth.positions, np.unwrap(truth.yaws)
    standing = np.flatnonzero(flown[:, 2] > flown[0, 2] + 0.02)[0] - 1
    airborne = np.flatnonzero(flown[:, 2] > 0.3)
    flying = slice(standing, airborne[-1] + 1)
    # it went, and turned (12.7 degrees in all since 2026-12-05's clock fix; 15 and more before)
    assert np.ptp(flown[flying, 0]) > 4.0 and np.ptp(yaw) > np.radians(10.0)
    recorded = read_groundtruth(out)
    at = np.searchsorted(recorded.t_ns, (t[flying] - t[0]) * 1e9)
    error = np.linalg.norm(recorded.position[at] - flown[flying], axis=1)
    assert np.median(error) < 0.15 and error.max() < 0.35, (np.median(error), error.max())
    recorded_yaw = np.array([yaw_of(quat_to_rot(q)) for q in recorded.q_W_B[at]])
    yaw_error = np.degrees(np.angle(np.exp(1j * (recorded_yaw - yaw[flying]))))
    assert np.abs(yaw_error).max() < 3.0, np.abs(yaw_error).max()
    assert recorded.t_ns[-1] * 1e-9 == pytest.approx(t[airborne[-1]] - t[0] + 1.0, abs=0.01)


def test_a_flight_recorded_by_another_version_can_be_flown_again(recording, tmp_path):
    """``--along`` needs only a recording's mission, its simulator profile and its true poses:
    a flight whose recorded config holds a key this version does not know (one since removed,
    or added by a newer one), which ``companion replay`` refuses, still gives its path."""
    from mcap.reader import make_reader

    from companion.recording import topics
    from companion.recording.replay import flown_path
    from companion.recording.writer import COMPANION_METADATA

    source, copy = recording["recording"]["path"], tmp_path / "other-version.mcap"
    with open(source, "rb") as recorded, open(copy, "wb") as out:
        reader = make_reader(recorded)
        metadata = next(record.metadata for record in reader.iter_metadata()
                        if record.name == COMPANION_METADATA)
        writer = mcap.writer.Writer(out)
        writer.start()
        writer.add_metadata(COMPANION_METADATA, {
            **metadata, "config": metadata["config"] + "\n[vins_future]\nknob = 1\n"})
        channels = {}
        for schema, channel, message in reader.iter_messages(topics=[topics.TRANSFORMS.name]):
            if channel.id not in channels:
                schema_id = writer.register_schema(schema.name, schema.encoding, schema.data)
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_id)
            writer.add_message(channels[channel.id], message.log_time, message.data,
                               message.publish_time)
        writer.finish()
    assert cli.main(["replay", str(copy)]) == 2  # the replay needs the config itself
    original, other = flown_path(source), flown_path(copy)
    assert (other.world, other.seed, other.profile) == (original.world, original.seed, "ideal")
    np.testing.assert_array_equal(other.positions, original.positions)
    np.testing.assert_array_equal(other.times, original.times)


def _log_vins(recording) -> list[dict]:
    code, out, _ = companion_log("vins", recording["recording"]["path"], "--json")
    assert code == 0
    return json.loads(out)


def test_replay_refuses_what_it_cannot_read(tmp_path, capsys):
    assert cli.main(["replay", str(tmp_path / "missing.mcap")]) == 1
    assert "no such file" in capsys.readouterr().err
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    assert cli.main(["replay", str(junk)]) == 1
    assert "not a readable MCAP recording" in capsys.readouterr().err


@pytest.mark.parametrize("until", ["0", "-3", "nan", "inf", "soon"])
def test_replay_refuses_a_span_that_is_not_a_positive_number(until, capsys):
    assert cli.main(["replay", "flight.mcap", "--until", until]) == 2
    assert f"--until: expected a positive number, got '{until}'" in capsys.readouterr().err


@pytest.mark.parametrize("until_s", [0.0, -3.0, math.nan, math.inf])
def test_the_library_refuses_such_a_span_before_reading_anything(until_s):
    from companion.recording.replay import replay as replay_recording

    with pytest.raises(ValueError, match="until_s must be a number of seconds above 0"):
        replay_recording("no such file.mcap", load_config(None), None, until_s)


def test_replay_reports_a_bad_override_as_a_config_error(recording, capsys):
    assert cli.main(["replay", recording["recording"]["path"], "--set",
                     "rescale.method=magic"]) == 2
    assert "rescale.method" in capsys.readouterr().err


@pytest.mark.parametrize("mission, words", [
    ({"world": "mars", "faults": []}, "unknown world 'mars'"),
    ({"world": "dome", "seed": "x", "faults": []}, "seed must be a non-negative integer"),
    ({"world": "dome", "pair": 99, "faults": []}, "dome has start/goal pairs 0..5"),
    ({"world": "dome", "faults": [{"kind": "gremlins"}]}, "unknown fault 'gremlins'"),
    ({"world": "dome", "faults": [{"when": 1}]}, "not a simulated mission"),
    ({"world": "dome", "planet": "mars"}, "not a simulated mission"),
    ({"world": "dome", "faults": 3}, "not a simulated mission"),
    ({"world": "dome", "goal": [1, 2, 1.5], "via": [[1, 2]]},
     "via waypoint 1 must be three finite numbers x,y,z, got \\(1, 2\\)"),
    ({"world": "dome", "goal": [1, 2, 1.5], "via": 5}, "not a simulated mission"),
    ({"world": "dome", "via": [[1, 2, 1.5]]}, "need a goal"),
])
def test_a_top_view_of_a_damaged_mission_record_says_what_is_wrong(recording, mission, words,
                                                                   tmp_path):
    """The recording's mission record drives the top view's world and route: one that is
    not a mission (the fuzzing review's finding) is a ReplayError naming it, never a
    TypeError from the simulator's constructors."""
    from companion.recording.replay import ReplayError, plot

    with pytest.raises(ReplayError, match=words):
        plot(recording["recording"]["path"], mission, load_config(None),
             tmp_path / "top.png")
    assert not (tmp_path / "top.png").exists()


def test_a_mission_record_reads_back_as_the_mission_flown():
    """What the recorder writes (the mission as JSON) reads back equal, its waypoints, goal and
    faults tuples again (a mission is a key of the flights flown)."""
    from companion.recording.replay import simulated_mission

    mission = SimMission(world="sewer", pair=5, goal=(39.0, 12.0, 1.5),
                         via=((34.0, 7.0, 1.5), (35.0, 8.0, 1.5)),
                         faults=(Fault("imu_gap", 2.0, 0.5),))
    assert simulated_mission(json.loads(json.dumps(dataclasses.asdict(mission)))) == mission


def empty_recording(path):
    """``path``, made a valid MCAP file with no message in it."""
    with open(path, "wb") as file:
        writer = mcap.writer.Writer(file)
        writer.start()
        writer.finish()
    return path


def companion_log(action: str, path, *options) -> tuple[int, str, str]:
    """``companion log ACTION PATH OPTIONS``'s exit code, stdout and stderr."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(["log", action, str(path), *options])
    return code, out.getvalue(), err.getvalue()


def test_log_vins_scores_the_vins_against_where_the_simulator_had_the_vehicle(recording):
    """A simulated flight records the true pose with each frame; `log vins` puts the VINS's
    estimate beside it, frame by frame, in PX4's local frame."""
    code, out, _ = companion_log("vins", recording["recording"]["path"], "--json")
    assert code == 0
    samples = json.loads(out)
    times = [sample["t"] for sample in samples]
    assert len(samples) > 150 and times == sorted(times)
    # The first true pose is the vehicle on the ground where the simulator started it.
    assert np.allclose(samples[0]["truth_position"], recording["start"], atol=0.01)
    errors = np.array([sample["error_m"] for sample in samples])
    assert np.isfinite(errors).all() and errors.max() < 0.5  # 12 s in the dome
    assert {sample["state"] for sample in samples} <= {"ok", "degraded", "lost", "initialising"}
    # the truth's heading is the one the error is taken against
    assert all(abs(s["truth_yaw_deg"]) <= 180.0 for s in samples)
    code, table, _ = companion_log("vins", recording["recording"]["path"], "--every", "4")
    assert code == 0 and "VINS error at the end" in table
    assert len(table.splitlines()) >= 3 + 3  # a row at least every 4 s of the flight
    accrued = table.splitlines()[1]
    assert accrued.startswith("heading error accrued turning (over 10°/s:"), accrued
    turning, straight = (float(words.split("°")[0]) for words in accrued.split(") ")[1:])
    assert turning + straight == pytest.approx(
        samples[-1]["heading_deg"] - samples[0]["heading_deg"], abs=0.02)
    # the tilt errors are in the table's row beside the heading's, and small in 12 s
    assert all(abs(s["pitch_deg"]) < 2.0 and abs(s["roll_deg"]) < 2.0 for s in samples)
    assert "   pitch     roll  state" in table.splitlines()[4]
    first_row = table.splitlines()[5].split()
    assert [float(word.rstrip("°")) for word in first_row[4:6]] == [
        pytest.approx(samples[0]["pitch_deg"], abs=0.006),
        pytest.approx(samples[0]["roll_deg"], abs=0.006)]
    # the estimate beside the truth is the error's other end
    for sample in samples[::50]:
        assert np.linalg.norm(np.subtract(sample["estimate_position"], sample["truth_position"])) \
            == pytest.approx(sample["error_m"])
    split = table.splitlines()[2]
    assert split.startswith("error at the end over the "), split
    assert table.splitlines()[3].startswith("path length by speed: 0.3-1.25 m/s ")
    flown = np.subtract(samples[-1]["truth_position"], samples[0]["truth_position"])[:2]
    assert float(split.split(" m flown")[0].split()[-1]) == pytest.approx(
        np.linalg.norm(flown), abs=0.05)


def _displaced_samples(truth_end, estimate_end, estimate_start=(0.0, 0.0, 0.0)):
    from companion.recording.replay import VinsErrorSample

    ends = [((0.0, 0.0, 0.0), estimate_start), (truth_end, estimate_end)]
    return [VinsErrorSample(t=float(k), truth_position=truth, truth_yaw_deg=0.0,
                            error_m=float(np.linalg.norm(np.subtract(estimate, truth))),
                            heading_deg=0.0, state="ok", landmarks=50, estimate_position=estimate)
            for k, (truth, estimate) in enumerate(ends)]


def test_the_error_at_the_end_is_split_into_the_paths_scale_bearing_and_height():
    """40 m flown north-east; the VINS has it 2 % short, turned 1 degree to the left, 0.3 m
    high, from a first frame 5 cm off: the split gives each back, and the first frame's error
    plus the along and across parts are the horizontal error at the end exactly."""
    from companion.recording.replay import displacement_split

    heading, bearing = math.radians(45.0), math.radians(1.0)
    truth_end = (40.0 * math.cos(heading), 40.0 * math.sin(heading), 0.5)
    start = (0.05, 0.0, 0.0)
    flown = 0.98 * 40.0
    estimate_end = (start[0] + flown * math.cos(heading + bearing),
                    start[1] + flown * math.sin(heading + bearing), 0.8)
    split = displacement_split(_displaced_samples(truth_end, estimate_end, start))
    assert split.distance_m == pytest.approx(40.0)
    assert split.scale == pytest.approx(0.98) and split.bearing_deg == pytest.approx(1.0)
    assert split.height_m == pytest.approx(0.3) and split.start_m == pytest.approx(0.05)
    assert split.along_m == pytest.approx(flown * math.cos(bearing) - 40.0)
    assert split.across_m == pytest.approx(flown * math.sin(bearing)) and split.across_m > 0
    along, across = np.array([math.cos(heading), math.sin(heading)]), \
        np.array([-math.sin(heading), math.cos(heading)])
    assert np.allclose(np.array(start[:2]) + split.along_m * along + split.across_m * across,
                       np.subtract(estimate_end, truth_end)[:2])


def test_the_paths_length_error_is_split_by_the_speed_it_was_flown_at():
    """Ten seconds hovering, 10 s east at 1 m/s read exactly, then 10 s north at 2 m/s read
    2 % short and 3 degrees off: each band gets its own seconds, metres and length error (the
    heading's error moves the estimate across, not along); the hover is in no band."""
    from companion.recording.replay import VinsErrorSample, length_accrual

    samples, truth, estimate = [], np.zeros(3), np.zeros(3)
    turned = np.array([[math.cos(0.05), -math.sin(0.05)], [math.sin(0.05), math.cos(0.05)]])
    for k in range(600):  # 20 Hz
        t = k / 20.0
        if 10.0 <= t < 20.0:
            step = np.array([0.05, 0.0])
            truth[:2] += step
            estimate[:2] += step
        elif t >= 20.0:
            step = np.array([0.0, 0.1])
            truth[:2] += step
            estimate[:2] += 0.98 * turned @ step
        samples.append(VinsErrorSample(t=t, truth_position=tuple(truth), truth_yaw_deg=0.0,
                                       error_m=0.0, heading_deg=0.0, state="ok", landmarks=50,
                                       estimate_position=tuple(estimate)))
    accrued = length_accrual(samples)
    assert list(accrued) == ["0.3-1.25 m/s", "1.25-1.75 m/s", "over 1.75 m/s"]
    slow, middle, fast = accrued.values()
    assert slow.seconds == pytest.approx(10.0, abs=0.6)
    assert slow.flown_m == pytest.approx(10.0, abs=0.2)
    assert slow.along_m == pytest.approx(0.0, abs=0.01)  # one step straddles the turn north
    assert middle.seconds == 0.0 and middle.flown_m == 0.0
    # less the step that straddles the turn and the last, under a whole step
    assert 18.5 <= fast.flown_m <= 20.0
    assert fast.along_m / fast.flown_m == pytest.approx(0.98 * math.cos(0.05) - 1.0, abs=1e-9)


def test_the_error_is_not_split_over_a_flight_that_went_nowhere():
    """Under a metre from the first frame (a hover, a flight back to its start), or samples
    without the estimate (made by hand, a flight without a pose): no split, not a ratio of
    noise."""
    from companion.recording.replay import displacement_split

    assert displacement_split(_displaced_samples((0.6, 0.6, 2.0), (0.7, 0.6, 2.0))) is None
    assert displacement_split(_yaw_samples([0.0, 0.0], [0.0, 0.0])) is None
    assert displacement_split(_displaced_samples((5.0, 0.0, 0.0), (5.0, 0.0, 0.0))[:1]) is None


@pytest.mark.parametrize("yaw_deg", [0.0, 35.0, -120.0, 180.0])
def test_a_tilt_error_is_split_about_the_true_heading(yaw_deg):
    """An estimate pitched nose down by 0.8 deg and rolled right by 0.3 deg off the truth, at
    any heading, reads so; the heading's own error is no tilt."""
    from companion.recording.replay import tilt_error_deg

    R_truth = so3_exp([0.0, 0.0, math.radians(yaw_deg)]) @ so3_exp([0.02, -0.05, 0.0])
    yaw = math.radians(yaw_deg)
    left, forward = np.array([-math.sin(yaw), math.cos(yaw), 0.0]), np.array(
        [math.cos(yaw), math.sin(yaw), 0.0])
    tilt = so3_exp(math.radians(0.8) * left + math.radians(0.3) * forward)
    pitch, roll = tilt_error_deg(tilt @ R_truth, R_truth)
    assert (pitch, roll) == (pytest.approx(0.8, abs=1e-3), pytest.approx(0.3, abs=1e-3))
    # nose down: the estimate's body x points lower than the truth's; right side down: its
    # body y (left) higher
    assert (tilt @ R_truth)[2, 0] < R_truth[2, 0] and (tilt @ R_truth)[2, 1] > R_truth[2, 1]
    assert tilt_error_deg(so3_exp([0.0, 0.0, 0.01]) @ R_truth, R_truth) == (
        pytest.approx(0.0, abs=1e-9), pytest.approx(0.0, abs=1e-9))


def _yaw_samples(truth_yaw_deg, heading_deg, dt=0.1):
    from companion.recording.replay import VinsErrorSample

    return [VinsErrorSample(t=k * dt, truth_position=(0.0, 0.0, 1.0), truth_yaw_deg=truth,
                            error_m=0.0, heading_deg=heading, state="ok", landmarks=50)
            for k, (truth, heading) in enumerate(zip(truth_yaw_deg, heading_deg))]


def test_the_heading_error_is_split_between_turning_and_straight_flight():
    """A 90 degree turn at 90 deg/s across the +-180 seam that adds half a degree of heading
    error, then 2 s straight that take 0.2 degrees away (its yaw wandering at 2 deg/s, under
    the turning rate), the error also across its own seam: each change goes to its kind."""
    from companion.recording.replay import heading_accrual

    turn = [135.0 + 9.0 * k for k in range(11)]  # 135 -> 225, stored within +-180
    straight = [225.0 + 0.2 * (k % 2) for k in range(1, 21)]
    truth = [(yaw + 180.0) % 360.0 - 180.0 for yaw in turn + straight]
    error = [179.9 + 0.05 * k for k in range(11)] + [180.4 - 0.01 * k for k in range(1, 21)]
    heading = [(e + 180.0) % 360.0 - 180.0 for e in error]
    accrued = heading_accrual(_yaw_samples(truth, heading))
    assert accrued["turning"].seconds == pytest.approx(1.0)
    assert accrued["turning"].turned_deg == pytest.approx(90.0)
    assert accrued["turning"].error_change_deg == pytest.approx(0.5)
    assert accrued["straight"].seconds == pytest.approx(2.0)
    assert accrued["straight"].error_change_deg == pytest.approx(-0.2)
    # the same samples counted with a turning rate above the turn's: all of it straight
    slow = heading_accrual(_yaw_samples(truth, heading), turning_rate_deg_s=100.0)
    assert slow["turning"].seconds == 0.0
    assert slow["straight"].error_change_deg == pytest.approx(0.3)


def test_log_vins_map_scale_is_the_landmarks_depth_over_the_true_depth(recording):
    """The map scale of each frame: 1 for a map at the true scale (this one, to a percent or
    two); None before the VINS has landmarks."""
    code, out, _ = companion_log("vins", recording["recording"]["path"], "--json", "--map")
    assert code == 0
    samples = json.loads(out)
    scales = np.array([s["map_scale"] for s in samples if s["map_scale"] is not None])
    assert len(scales) > 0.8 * len(samples)
    assert abs(np.median(scales) - 1.0) < 0.02 and np.abs(scales - 1.0).max() < 0.1
    assert samples[0]["landmarks"] == 0 and samples[0]["map_scale"] is None
    code, table, _ = companion_log("vins", recording["recording"]["path"], "--map")
    assert code == 0 and "map scale" in table.splitlines()[4]


def test_log_vins_refuses_a_recording_without_the_truth_and_a_bad_interval(recording, tmp_path):
    code, _, err = companion_log("vins", empty_recording(tmp_path / "real.mcap"))
    assert code == 1 and "no true pose" in err and "only simulated flights" in err
    code, _, err = companion_log("vins", recording["recording"]["path"], "--every", "0")
    assert code == 1 and "--every must be above 0" in err
    # a file that is not there, or a folder: one line naming it, never a traceback
    for unreadable in (tmp_path / "missing.mcap", tmp_path):
        for action in ("vins", "time"):
            code, out, err = companion_log(action, unreadable)
            assert code == 1 and out == "" and err.count("\n") == 1, err
            assert err.startswith(f"log {action}: {unreadable}: cannot read: "), err


def test_log_time_splits_the_navigation_phase_over_what_the_vehicle_was_doing(recording):
    """The 12 s dome flight, ended by its 12 s mission timeout: its navigation phase (the
    summary's navigation_time_s, from the switch to Offboard) is spent on the offset swing,
    the planner's arcs, by speed tier, and the failsafe's stop, each as long as the
    transitions say (the stop to the hold, or the glide to a landing site); the arc rounds are
    the flight's planner rounds, which the summary counts too."""
    code, out, _ = companion_log("time", recording["recording"]["path"], "--json")
    assert code == 0
    spent = json.loads(out)
    assert spent["seconds"] == pytest.approx(recording["navigation_time_s"], abs=0.1)
    assert min(spent["activities"].values()) >= 0.0, spent["activities"]
    times = [t["t"] for t in recording["transitions"]]
    stop = [t["to"] for t in recording["transitions"]].index("failsafe_stop")
    assert spent["activities"]["the failsafe's stop"] == pytest.approx(
        times[stop + 1] - times[stop], abs=0.01)
    swing = [t["to"] for t in recording["transitions"]].index("calibrating")
    assert spent["activities"]["the offset swing"] == pytest.approx(
        times[swing + 1] - times[swing], abs=0.01)
    arcs = {label: s for label, s in spent["activities"].items() if label.startswith("arcs at")}
    assert arcs and sum(arcs.values()) > 0.5 * spent["seconds"], spent["activities"]
    rounds = recording["planning_rounds"]
    assert rounds - recording["stop_rounds"] <= spent["arc_rounds"] <= rounds
    assert 0.0 < spent["arc_round_gap_s"] < 0.5
    code, table, _ = companion_log("time", recording["recording"]["path"])
    assert code == 0 and "s of navigation" in table
    assert any("arcs at" in line for line in table.splitlines()[2:])


def test_log_time_refuses_a_recording_that_never_navigated(tmp_path):
    code, out, err = companion_log("time", empty_recording(tmp_path / "ground.mcap"))
    assert code == 1 and out == "" and "never navigated" in err and len(err.splitlines()) == 1
