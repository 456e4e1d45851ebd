"""The fuzz harnesses of fuzz/ (issue 27; fuzz/README.md, docs/reliability.md "Fuzzing"), run
briefly and deterministically: each on its seed corpus and a fixed number of seeded mutations
of it, each checking its invariant on every input; and every finding the fuzzers made, saved
under fuzz/regressions/, replayed to the clear error (or safe reaction) that fixed it.
"""

from __future__ import annotations

import importlib

import pytest

from fuzz import harness

#: Seeded mutations each harness runs besides its seed corpus (a few seconds in all).
MUTATIONS = {"mavlink_receive": 150, "config_set": 400, "euroc_reader": 400,
             "camera_truth_reader": 400, "mcap_reader": 150}
SEED = 27

#: What each finding (and each of the camera truth's refusals kept beside them) now gets: a
#: fragment of one of the messages ``run`` returns (the reader's error, or the driver's
#: counter of what it refused); None: the reader now reads it, and the invariant is the check.
UNREADABLE = "is not a readable MCAP recording"
EXPOSURES = "(the exposures, column 2)"
FINDINGS = {
    "camera_truth_reader/truth-exposure-beyond-int64": f"64-bit nanoseconds {EXPOSURES}",
    "camera_truth_reader/truth-exposure-not-an-integer": f"with base 10: '9.85e5') {EXPOSURES}",
    "camera_truth_reader/truth-exposures-out-of-order": f"not strictly increasing {EXPOSURES}",
    "camera_truth_reader/truth-of-fewer-frames": "data.csv (1 and 2 frames; frame 2 differs)",
    "camera_truth_reader/truth-of-other-frames": "data.csv (2 and 2 frames; frame 2 differs)",
    "camera_truth_reader/truth-without-the-table": "cam0/truth.csv: no such file",
    "camera_truth_reader/truth-without-the-yaml": "cam0/truth.yaml: no such file",
    "camera_truth_reader/truth-yaml-T_BS-not-rigid": "truth.yaml: T_BS is not a rigid transform",
    "config_set/set-arrays-nested-too-deep": "rescale.kappa: must be a number, got '[[[",
    "config_set/set-not-utf8": r"--set recorder.directory=/var/lib/\xff: not UTF-8 text",
    "config_set/toml-arrays-nested-too-deep": "invalid TOML: arrays or tables nested too deeply",
    "config_set/vehicle-thrust-max-below-hover": "vehicle.thrust_max: must exceed thrust_hover",
    "euroc_reader/camera-no-frames": "cam0/data.csv: no frames",
    "euroc_reader/camera-row-of-one-column": "cam0/data.csv: frame 1 has 1 columns, expected 2",
    "euroc_reader/camera-timestamps-repeated": "timestamps are not strictly increasing",
    "euroc_reader/camera-yaml-T_BS-not-a-matrix": "T_BS is not a list of numbers",
    "euroc_reader/camera-yaml-T_BS-not-rigid": "sensor.yaml: T_BS is not a rigid transform",
    "euroc_reader/camera-yaml-a-list-not-a-map": "cam0/sensor.yaml: not a YAML map of keys",
    "euroc_reader/camera-yaml-intrinsics-empty": "intrinsics has 0 numbers, expected 4",
    "euroc_reader/camera-yaml-resolution-not-a-list": "resolution is not a list of numbers",
    "euroc_reader/camera-yaml-resolution-of-three": "resolution has 3 numbers, expected 2",
    "euroc_reader/camera-yaml-without-T_BS-or-rate": "sensor.yaml: missing T_BS",
    "euroc_reader/camera-yaml-without-rate": "sensor.yaml: missing rate_hz",
    "euroc_reader/groundtruth-not-ascii": "data.csv: not ASCII text",
    "euroc_reader/groundtruth-timestamp-beyond-int64": "a timestamp beyond 64-bit nanoseconds",
    "euroc_reader/imu-not-finite": "imu0/data.csv: sample 1 holds a value that is not a finite",
    "mavlink_receive/home-position-not-finite": "home_position_unknown=1",
    "mavlink_receive/odometry-quaternion-not-unit": "state_invalid=1",
    "mcap_reader/replay-calibration-without-K": "/camera/calibration: not a camera model (K must",
    "mcap_reader/replay-chunk-not-utf8": f"{UNREADABLE} (UnicodeDecodeError",
    "mcap_reader/replay-event-not-a-transition": "/flight/events: not a state transition",
    "mcap_reader/replay-imu-record-without-accel": "a /imu record whose 'accel' is None",
    "mcap_reader/replay-json-record-broken": f"{UNREADABLE} (JSONDecodeError",
    "mcap_reader/replay-message-of-an-unknown-channel": f"{UNREADABLE} (KeyError: 255)",
    "mcap_reader/replay-metadata-record-cut": f"{UNREADABLE} (error: unpack requires",
    "mcap_reader/replay-record-length-huge": f"{UNREADABLE} (MemoryError",
    "mcap_reader/replay-schema-renames-a-field": None,
    "mcap_reader/replay-seek-before-the-start": f"{UNREADABLE} (OSError",
}


def _module(target: str):
    if target == "mavlink_receive":  # its inputs are read by atheris's FuzzedDataProvider
        pytest.importorskip("atheris")
    return importlib.import_module(f"fuzz.{target}")


def _run(module, data: bytes, tmp_path) -> list[str]:
    """``module.run(data)``; on a finding, the input is kept in ``tmp_path`` to reproduce."""
    try:
        return module.run(data)
    except BaseException:
        (tmp_path / "finding").write_bytes(data)
        print(f"the input is {tmp_path / 'finding'}: python fuzz/{module.TARGET}.py FILE")
        raise


# A hostile PX4's NaN and infinite quaternions make numpy warn as the driver converts them
# (before it refuses the estimate they are in).
@pytest.mark.filterwarnings("ignore::RuntimeWarning")
@pytest.mark.parametrize("target", sorted(MUTATIONS))
def test_the_seed_corpus_and_its_mutations_keep_the_invariant(target, tmp_path):
    module = _module(target)
    seeds = harness.corpus(target)
    assert seeds, f"fuzz/corpus/{target} is empty"
    for data in seeds + list(harness.mutations(seeds, MUTATIONS[target], SEED)):
        _run(module, data, tmp_path)


def test_the_mutations_are_the_same_on_every_run():
    seeds = [b"0123456789", b"abc"]
    assert list(harness.mutations(seeds, 50, SEED)) == list(harness.mutations(seeds, 50, SEED))
    assert len(set(harness.mutations(seeds, 50, SEED))) > 40


def test_the_camera_truths_seeds_read_whole_half_and_none():
    """The camera truth harness's seeds (fuzz/seeds.py), in file-name order: its valid files
    read as a whole truth; with files left out, half a truth is named and none is None."""
    said = [_module("camera_truth_reader").run(data)
            for data in harness.corpus("camera_truth_reader")]
    assert said == [[], [], ["mav0/cam0/truth.yaml: no such file"],
                    ["mav0/cam0/truth.csv: no such file"], ["no truth"], []]


@pytest.mark.parametrize("finding", sorted(
    f"{target}/{path.name}" for target in MUTATIONS for path in harness.regressions(target)))
def test_every_finding_keeps_the_invariant_and_gets_its_clear_error(finding, tmp_path):
    target, name = finding.split("/")
    said = _run(_module(target), (harness.FUZZ / "regressions" / target / name).read_bytes(),
                tmp_path)
    assert finding in FINDINGS, f"fuzz/regressions/{finding} has no expectation in FINDINGS"
    expected = FINDINGS[finding]
    assert expected is None or any(expected in line for line in said), said
