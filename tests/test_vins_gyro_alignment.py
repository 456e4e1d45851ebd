"""Issue 24: the gyro's response to the yaw rate, estimated online against the camera's
rotation and corrected (autonomy/vins/gyro_alignment.py, docs/vins.md).

A gyro whose x and y axes respond to the z rate integrates false tilt in every corner, which
the smoother takes for an accelerometer bias. First the estimator on the synthetic flight of
tests/test_vins_time_offset.py (exact geometry, a gyro with a known misalignment); then the
correction's algebra; then the options and the whole VINS on a simulated flight.
"""

import math

import numpy as np
import pytest

from autonomy.geometry import PinholeCamera, so3_exp
from autonomy.messages import ImuSample
from autonomy.options import OptionError
from autonomy.vins import Vins, VinsOptions
from autonomy.vins.gyro_alignment import GyroAlignment
from autonomy.vins.preintegration import ImuNoise, exp_and_right_jacobian
from autonomy.vins.time_offset import PairRotations
from tests.test_vins_time_offset import _synthetic_flight

#: A misalignment of the size the realistic profile draws: x and y respond to the z rate by
#: 2 % and -1.5 %, z reads 0.4 % high.
COLUMN = np.array([0.02, -0.015, 0.004])


def _gyro_matrix(column):
    matrix = np.eye(3)
    matrix[:, 2] += column
    return matrix


def _aligned_on_synthetic_flight(column, td=0.0, prior=(0.0, 0.0, 0.0)):
    """The alignment (its prior's mean ``prior``) fed the time-offset estimator's pairs over
    the synthetic flight (a camera stamped ``td`` late), once the offset is known, as the VINS
    feeds it."""
    options = VinsOptions(estimate_time_offset=True)
    alignment = GyroAlignment(0.014, 0.005, prior)
    history = []

    def feed(estimator):
        sigma = estimator.offset.sigma
        if estimator.latest_pair is not None and sigma is not None \
                and sigma <= options.time_offset_max_sigma_s:
            alignment.add_pair(estimator.latest_pair)
        history.append(alignment.column)

    _synthetic_flight(td, options, gyro_matrix=_gyro_matrix(column), on_frame=feed)
    return alignment, np.array(history)


@pytest.mark.parametrize("td", [0.0, 0.015])
def test_a_hidden_yaw_response_is_found_once_the_vehicle_turns(td):
    alignment, history = _aligned_on_synthetic_flight(COLUMN, td)
    straight = history[: int(2.9 / 0.05)]
    # flying straight the pairs say nothing about a yaw response: the estimate stays at zero
    assert np.abs(straight).max() < 1e-3
    estimate = alignment.estimate
    error = np.asarray(estimate.column) - COLUMN
    assert np.abs(error).max() < 0.001, estimate
    assert np.all(np.abs(error) < 3 * np.asarray(estimate.sigma))  # the sigma is honest
    assert estimate.pairs > 50


def test_a_carried_calibration_holds_from_the_start_and_the_flight_refines_it():
    """An earlier flight's column, off by about its sigma there: flying straight it is the
    correction as given, and the corners bring it to this flight's."""
    carried = COLUMN + np.array([0.004, -0.004, 0.001])
    alignment, history = _aligned_on_synthetic_flight(COLUMN, prior=carried)
    straight = history[: int(2.9 / 0.05)]
    np.testing.assert_allclose(straight, np.tile(carried, (len(straight), 1)), atol=1e-3)
    assert np.abs(alignment.column - COLUMN).max() < 0.001, alignment.estimate


@pytest.mark.parametrize("prior", [(0.01, 0.02), (0.0, math.nan, 0.0), (0.0, 0.0, -1.0)])
def test_a_prior_mean_that_is_not_a_column_is_refused(prior):
    with pytest.raises(ValueError, match="prior's mean"):
        GyroAlignment(0.014, 0.005, prior)


def test_an_exact_gyro_gives_no_correction():
    alignment, _ = _aligned_on_synthetic_flight(np.zeros(3))
    assert np.abs(alignment.column).max() < 0.002


def test_large_turns_one_way_round_give_the_column_without_a_twist():
    """Pairs of up to 0.8 rad of yaw, all one way: the regressor's right Jacobian keeps the
    fitted x and y responses from turning by half the yaw."""
    alignment = GyroAlignment(0.014, 0.005)
    information = np.eye(3) / 3e-4 ** 2
    for yaw in np.linspace(0.1, 0.8, 60):
        theta = np.array([0.01, -0.02, yaw])
        true_gyro = so3_exp(_gyro_matrix(COLUMN) @ theta)
        alignment.add_pair(PairRotations(true_gyro, so3_exp(theta), information, 1.0))
    assert np.abs(alignment.column - COLUMN).max() < 2e-4


#: A whole misalignment of the realistic profile's size (by rows): the roll axis responds to
#: the pitch rate by -2 %, the yaw axis to the roll rate by -2.7 % (mine seed 15's, with its
#: camera mounting's).
MATRIX = np.array([[0.002, -0.023, -0.010], [0.012, 0.003, -0.009], [-0.030, 0.015, 0.0]])


def _pairs_turning_every_way(matrix, count=400, seed=5):
    """Frame pairs of a vehicle that pitches and rolls as it speeds up, slows down and turns
    (each axis up to 0.1 rad a pair), the camera exact, the gyro ``I + matrix``."""
    rng = np.random.default_rng(seed)
    information = np.eye(3) / 3e-4 ** 2
    for _ in range(count):
        theta = rng.uniform(-0.1, 0.1, 3)
        yield PairRotations(so3_exp((np.eye(3) + matrix) @ theta), so3_exp(theta), information,
                            1.0)


def test_the_whole_misalignment_is_found_when_the_vehicle_pitches_and_rolls_too():
    whole, yaw_only = GyroAlignment(0.014, 0.005, rates="all"), GyroAlignment(0.014, 0.005)
    for pair in _pairs_turning_every_way(MATRIX):
        whole.add_pair(pair)
        yaw_only.add_pair(pair)
    assert np.abs(whole.matrix - MATRIX).max() < 5e-4, whole.matrix
    np.testing.assert_allclose(whole.column, MATRIX[:, 2], atol=5e-4)
    estimate = whole.estimate
    assert np.all(np.abs(whole.matrix - MATRIX) < 3 * np.asarray(estimate.matrix_sigma) + 1e-4)
    np.testing.assert_allclose(estimate.matrix, whole.matrix)
    # the yaw column alone leaves the roll and pitch rates' responses uncorrected, and the
    # pairs' unexplained roll and pitch pull its column off
    assert yaw_only.estimate.matrix is None and np.all(yaw_only.matrix[:, :2] == 0.0)


def test_a_carried_whole_misalignment_corrects_every_rate_and_the_yaw_column_is_refined():
    """Nine numbers by rows carried over, the yaw column estimated: the roll and pitch rates'
    responses stay as carried, and the summary shows the whole matrix in use."""
    alignment = GyroAlignment(0.014, 0.005, tuple(MATRIX.reshape(-1)))
    rate = np.array([0.3, -0.2, 0.5])
    np.testing.assert_allclose(alignment.correct((np.eye(3) + MATRIX) @ rate), rate, atol=1e-15)
    np.testing.assert_allclose(alignment.uncorrect(rate), (np.eye(3) + MATRIX) @ rate, atol=1e-15)
    for pair in _pairs_turning_every_way(MATRIX + np.array([[0, 0, 0.004]] * 3)):
        alignment.add_pair(pair)
    np.testing.assert_array_equal(alignment.matrix[:, :2], MATRIX[:, :2])
    np.testing.assert_allclose(alignment.column, MATRIX[:, 2] + 0.004, atol=5e-4)
    assert np.all(np.asarray(alignment.estimate.matrix_sigma)[:, :2] == 0.0)


def test_a_whole_misalignment_needs_a_known_rate_choice():
    with pytest.raises(ValueError, match="rates must be one of"):
        GyroAlignment(0.014, 0.005, rates="roll")


def test_the_right_jacobian_is_the_first_order_of_exp():
    rng = np.random.default_rng(4)
    for phi in (rng.normal(size=3) * 0.7, np.array([0.0, 0.0, 1e-8])):
        d = rng.normal(size=3) * 1e-6
        expected = so3_exp(phi).T @ so3_exp(phi + d)
        np.testing.assert_allclose(expected, so3_exp(exp_and_right_jacobian(phi[None])[1][0] @ d), atol=1e-11)


def test_the_correction_inverts_the_misalignment_exactly():
    alignment = GyroAlignment(0.014, 0.005, COLUMN)
    rate = np.array([0.1, -0.3, 0.8])
    measured = _gyro_matrix(COLUMN) @ rate
    np.testing.assert_allclose(alignment.correct(measured), rate, atol=1e-15)
    np.testing.assert_allclose(alignment.uncorrect(rate), measured, atol=1e-15)


def test_a_wild_pair_moves_the_estimate_only_boundedly():
    """A pair whose camera rotation is badly wrong (a mismatched frame) has a Huber weight."""
    good, wild = GyroAlignment(0.014, 0.005), GyroAlignment(0.014, 0.005)
    rng = np.random.default_rng(3)
    information = np.eye(3) / 3e-4 ** 2
    for _ in range(200):
        theta = np.array([0.0, 0.0, rng.uniform(-0.2, 0.2)])
        pair = PairRotations(so3_exp(_gyro_matrix(COLUMN) @ theta), so3_exp(theta), information,
                             1.0)
        good.add_pair(pair)
        wild.add_pair(pair)
    wild.add_pair(PairRotations(np.eye(3), so3_exp(np.array([0.2, -0.1, 0.3])), information,
                                1.0))
    assert np.abs(good.column - COLUMN).max() < 0.001
    assert np.abs(wild.column - good.column).max() < 0.002


def test_a_non_finite_pair_or_a_bad_overlap_is_ignored():
    alignment = GyroAlignment(0.014, 0.005)
    bad = np.full((3, 3), np.nan)
    turn = so3_exp(np.array([0.0, 0.0, 0.3]))
    alignment.add_pair(PairRotations(bad, turn, np.eye(3), 1.0))
    alignment.add_pair(PairRotations(turn, turn, bad, 1.0))
    for overlap in (0.0, -0.5, 1.5, math.nan):
        alignment.add_pair(PairRotations(np.eye(3), turn, np.eye(3) * 1e6, overlap))
    assert alignment.estimate.pairs == 0 and alignment.estimate.sigma is None
    assert np.all(alignment.column == 0.0)


def test_a_pair_without_information_says_nothing():
    alignment = GyroAlignment(0.014, 0.005)
    alignment.add_pair(PairRotations(np.eye(3), so3_exp(np.array([0.0, 0.0, 0.3])),
                                     np.zeros((3, 3)), 1.0))
    assert np.all(alignment.column == 0.0)
    np.testing.assert_allclose(alignment.estimate.sigma, (0.014, 0.014, 0.005))


@pytest.mark.parametrize("sigmas", [(0.0, 0.005), (0.014, -1.0), (math.nan, 0.005)])
def test_a_prior_without_a_positive_sigma_is_refused(sigmas):
    with pytest.raises(ValueError, match="sigmas must be positive"):
        GyroAlignment(*sigmas)


# ------------------------------------------------------------------ options and the VINS


@pytest.mark.parametrize("changes, key", [
    ({"estimate_gyro_alignment": True}, "estimate_gyro_alignment"),  # without the pairs
    ({"gyro_cross_axis_sigma": 0.0}, "gyro_cross_axis_sigma"),
    ({"gyro_scale_sigma": math.inf}, "gyro_scale_sigma"),
    ({"estimate_gyro_alignment": "yes"}, "estimate_gyro_alignment"),
    ({"gyro_alignment": (0.01, 0.02)}, "gyro_alignment"),
    ({"gyro_alignment": (0.01, math.nan, 0.0)}, "gyro_alignment"),
    ({"gyro_alignment": (0.5, 0.0, 0.0)}, "gyro_alignment"),
    ({"gyro_alignment": (0.0,) * 8}, "gyro_alignment"),  # nine by rows, or three
    ({"gyro_alignment_rates": "roll"}, "gyro_alignment_rates"),
])
def test_bad_alignment_options_are_refused_with_their_name(changes, key):
    with pytest.raises(OptionError) as error:
        VinsOptions(**changes)
    assert error.value.key == key


def test_the_alignment_is_off_by_default():
    assert VinsOptions().estimate_gyro_alignment is False
    assert VinsOptions().gyro_alignment == (0.0, 0.0, 0.0)
    assert VinsOptions().gyro_alignment_rates == "yaw"
    assert len(VinsOptions(gyro_alignment=(0.01,) * 9).gyro_alignment) == 9


def test_with_the_alignment_on_a_bad_imu_sample_is_refused_and_the_estimator_goes_on():
    camera = PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5)
    vins = Vins(camera, (), np.eye(4), ImuNoise(),
                VinsOptions(estimate_time_offset=True, estimate_gyro_alignment=True))
    vins.add_imu(ImuSample(0.0, np.zeros(3), np.array([0.0, 0.0, 9.81])))
    with pytest.raises(ValueError, match="NaN"):
        vins.add_imu(ImuSample(0.005, np.array([0.0, math.nan, 0.1]), np.zeros(3)))
    with pytest.raises(ValueError, match="3 values"):
        vins.add_imu(ImuSample(0.005, np.zeros(2), np.zeros(3)))
    vins.add_imu(ImuSample(0.005, np.zeros(3), np.array([0.0, 0.0, 9.81])))


# ------------------------------------------------------------------ the VINS through a corner

CORNER_FLIGHT_S = 22.0  # mine, seed 0: the route's first corner, a 90 deg yaw, at 16-20 s


def _misalign_gyro(source, target, column):
    """``target``: the recording ``source`` with its gyro reading ``(I + column z^T)`` times
    the rate (everything else shared through symbolic links)."""
    for name in ("cam0", "depth0", "state_groundtruth_estimate0"):
        if (source / "mav0" / name).is_dir():
            (target / "mav0").mkdir(parents=True, exist_ok=True)
            (target / "mav0" / name).symlink_to((source / "mav0" / name).resolve())
    imu = target / "mav0" / "imu0"
    imu.mkdir(parents=True)
    (imu / "sensor.yaml").symlink_to((source / "mav0" / "imu0" / "sensor.yaml").resolve())
    lines = (source / "mav0" / "imu0" / "data.csv").read_text().splitlines()
    rows = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
    rows[:, 1:4] = rows[:, 1:4] @ _gyro_matrix(column).T
    body = "\n".join(f"{int(r[0])}," + ",".join(f"{v:.9g}" for v in r[1:]) for r in rows)
    (imu / "data.csv").write_text(lines[0] + "\n" + body + "\n")
    return target


@pytest.fixture(scope="module")
def corner_runs(record_flight, tmp_path_factory):
    """The VINS over the corner flight with a hidden yaw response, without and with the
    alignment, and with the column as a calibration carried over (a fixed correction): their
    ``eval vio`` scores."""
    from companion.tools.eval import vio

    source = record_flight("mine", CORNER_FLIGHT_S)
    root = _misalign_gyro(source, tmp_path_factory.mktemp("misaligned"), COLUMN)
    arms = {False: {}, True: {"estimate_gyro_alignment": True},
            "carried": {"gyro_alignment": tuple(COLUMN)}}
    return {arm: vio.evaluate_vio(root, VinsOptions(estimate_time_offset=True, **changes),
                                  consistency=False)
            for arm, changes in arms.items()}


def test_the_vins_finds_a_hidden_yaw_response_in_a_corner(corner_runs):
    alignment = corner_runs[True]["gyro_alignment"]
    assert corner_runs[False]["gyro_alignment"] is None
    error, sigma = np.asarray(alignment["column"]) - COLUMN, np.asarray(alignment["sigma"])
    # one corner pins the column to well under the prior's 0.014, and the truth lies within
    # three of the estimate's own sigmas
    assert np.all(sigma < 0.006), alignment
    assert np.all(np.abs(error) < 3 * sigma), alignment
    assert alignment["pairs"] > 200


def test_correcting_the_yaw_response_makes_the_flight_more_accurate(corner_runs):
    off, on = corner_runs[False], corner_runs[True]
    assert on["resets"] == 0
    assert on["ate_over_distance"] < off["ate_over_distance"], (on, off)


def test_a_carried_calibration_corrects_the_corner_without_estimating(corner_runs):
    from companion.tools.eval.vio import format_vio_report

    off, carried = corner_runs[False], corner_runs["carried"]
    assert carried["gyro_alignment"] == {"column": list(COLUMN), "sigma": None, "pairs": 0,
                                         "matrix": None, "matrix_sigma": None}
    assert "+0.0200 -0.0150 +0.0040 as given" in format_vio_report(carried)
    assert "yaw rate (x, y, z): not corrected" in format_vio_report(off)
    assert carried["resets"] == 0
    assert carried["ate_over_distance"] < off["ate_over_distance"], (carried, off)
