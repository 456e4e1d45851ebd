"""How much of the VINS's error at the end of navigation the vehicle's calibration explains,
behind ``companion eval nav --calibration``.

Two of a simulated vehicle's calibration errors turn into the error at the goal whatever the
estimator does (docs/vins.md): the camera's yaw on the body, ``dz``, turns the whole path the
VINS reckons by about ``-dz`` (a forward camera's yaw shows only through roll and pitch
rotations and the thrust's direction, which a multirotor's cruise hardly gives), and the
accelerometer's z sensitivity error ``s_z`` scales it (every acceleration a multirotor makes is
its thrust along the body's z). Over the flights of ``eval nav`` records, each vehicle drawn
again from its record's seed (:func:`drivers.sim.host.vehicle_errors`), this fits by least
squares

    bearing = a + b dz          (degrees),
    scale - 1 = a + b s_z       (per cent),

and reports the slopes, intercepts, the correlation ``r`` (over the flights, and over the
vehicles' means) and the residuals' standard deviation: what a better calibration would take
away, and what is left for the estimator (the intercept is its own bias, the residual its
spread). With the fitted parts taken out of each flight's split (``across - d sin(b dz)``,
``along - d b s_z``, the height as flown; ``d`` the distance from the start), it gives the error
at the end per depth source as issue 24 judges it (median, worst) beside the flown one: what
the fits leave to the estimator.
"""

from __future__ import annotations

import math
from typing import Callable, Iterable

import numpy as np

from companion.tools.eval.vio import EvaluationError

#: At least this many flights with a split error, and two vehicles, for a fit.
MIN_FLIGHTS = 3
#: The split's numbers a fit reads (``position_error_split``, :mod:`autonomy.trajectory`).
SPLIT_KEYS = ("distance_m", "scale", "bearing_deg", "along_m", "across_m", "height_m")


def calibration_fit(records: Iterable[dict], errors_of: Callable[[int], object]) -> dict:
    """The two fits (module docstring) over the ``records`` with a ``position_error_split``,
    ``errors_of(seed)`` giving each seed's :class:`~drivers.sim.host.VehicleErrors` (a vehicle
    is one set of errors: seeds flying one ``vehicle_seed`` are one); EvaluationError for a
    split without its numbers, fewer than :data:`MIN_FLIGHTS` such records or fewer than two
    vehicles (the ideal profile draws none)."""
    scored = [r for r in records if r.get("position_error_split")]
    for record in scored:
        _check_split(record)
    errors = {seed: errors_of(seed) for seed in sorted({r["seed"] for r in scored})}
    vehicle_ids = {e: i for i, e in enumerate(dict.fromkeys(errors.values()))}
    vehicles = len(vehicle_ids)
    if len(scored) < MIN_FLIGHTS or vehicles < 2:
        raise EvaluationError(f"a fit needs {MIN_FLIGHTS} flights with a VINS error at the end "
                              f"of two vehicles or more; got {len(scored)} flights of "
                              f"{vehicles} (the config given draws each seed's vehicle: "
                              "give the runs' own --config and --set)")
    splits = [r["position_error_split"] for r in scored]
    yaw = [errors[r["seed"]].mount_rotation_deg[2] for r in scored]
    accel_z = [100.0 * errors[r["seed"]].accel_scale_error[2] for r in scored]
    by_vehicle = [vehicle_ids[errors[r["seed"]]] for r in scored]
    bearing = _line([s["bearing_deg"] for s in splits], yaw, by_vehicle)
    scale = _line([100.0 * (s["scale"] - 1.0) for s in splits], accel_z, by_vehicle)
    return {
        "flights": len(scored), "vehicles": vehicles,
        "bearing_deg_on_mount_yaw_deg": bearing,
        "scale_error_pct_on_accel_z_error_pct": scale,
        "end_error_m": _end_errors(scored, yaw, accel_z, bearing["slope"] or 0.0,
                                   scale["slope"] or 0.0),
        "vehicles_drawn": {str(seed): {"mount_yaw_deg": round(v.mount_rotation_deg[2], 4),
                                       "accel_z_scale_error_pct":
                                           round(100.0 * v.accel_scale_error[2], 4)}
                           for seed, v in errors.items()},
    }


def _check_split(record: dict) -> None:
    split = record["position_error_split"]
    missing = [key for key in SPLIT_KEYS
               if type(split.get(key) if isinstance(split, dict) else None) not in (int, float)]
    if missing or type(record.get("position_error_m")) not in (int, float):
        raise EvaluationError(f"{record.get('world')} pair {record.get('pair')} "
                              f"{record.get('depth')} seed {record.get('seed')}: its VINS error "
                              f"at the end lacks {', '.join(missing) or 'position_error_m'}")


def _line(y: list[float], x: list[float], groups: list[int]) -> dict:
    """``y = intercept + slope x`` by least squares, with ``r`` over the points and over the
    means of each of ``groups`` (a vehicle; None under three: two means lie on a line), and
    the residuals' SD; the slope None where ``x`` does not vary (no vehicle drew this error)."""
    x_, y_ = np.asarray(x, float), np.asarray(y, float)
    if np.ptp(x_) == 0.0:
        return {"slope": None, "intercept": None, "r": None, "r_vehicles": None,
                "residual_sd": None, "sd": round(float(y_.std()), 4)}
    slope, intercept = np.polyfit(x_, y_, 1)
    residual = y_ - (intercept + slope * x_)
    group = np.asarray(groups)
    means = np.array([[x_[group == k].mean(), y_[group == k].mean()] for k in np.unique(group)])
    return {"slope": round(float(slope), 4), "intercept": round(float(intercept), 4),
            "r": _correlation(x_, y_), "r_vehicles": _correlation(means[:, 0], means[:, 1]),
            "residual_sd": round(float(residual.std()), 4), "sd": round(float(y_.std()), 4)}


def _correlation(x: np.ndarray, y: np.ndarray) -> float | None:
    r = float(np.corrcoef(x, y)[0, 1]) if len(x) > 2 and np.ptp(x) > 0.0 else math.nan
    return None if math.isnan(r) else round(r, 4)


def _end_errors(records: list[dict], yaw: list[float], accel_z: list[float],
                bearing_slope: float, scale_slope: float) -> dict:
    """Per depth source, the median and worst error at the end as flown and with the fitted
    calibration parts taken out of each split (module docstring), metres."""
    flown, left = {}, {}
    for record, dz, s_z in zip(records, yaw, accel_z):
        split = record["position_error_split"]
        d = split["distance_m"]
        across = split["across_m"] - d * math.sin(math.radians(bearing_slope * dz))
        along = split["along_m"] - d * scale_slope * s_z / 100.0
        flown.setdefault(record["depth"], []).append(record["position_error_m"])
        left.setdefault(record["depth"], []).append(math.hypot(across, along, split["height_m"]))
    return {depth: {"flown": _median_worst(flown[depth]),
                    "calibration_taken_out": _median_worst(left[depth])} for depth in flown}


def _median_worst(values: list[float]) -> dict:
    return {"median": round(float(np.median(values)), 4), "worst": round(max(values), 4)}


def format_markdown(fit: dict, runs: list[str]) -> str:
    """The fit as a short Markdown report."""
    lines = [f"VINS error at the end of navigation against the vehicles' calibration errors: "
             f"{fit['flights']} flights of {fit['vehicles']} vehicles ({', '.join(runs)}).", "",
             "| fit | slope | intercept | r (flights) | r (vehicles' means) | SD | residual SD |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for key, name in (("bearing_deg_on_mount_yaw_deg",
                       "bearing (°) on the camera's yaw on the body (°)"),
                      ("scale_error_pct_on_accel_z_error_pct",
                       "scale − 1 (%) on the accelerometer's z scale error (%)")):
        line = fit[key]
        lines.append(f"| {name} | {_number(line['slope'], '+')} | "
                     f"{_number(line['intercept'], '+')} | {_number(line['r'], '+')} | "
                     f"{_number(line['r_vehicles'], '+')} | {_number(line['sd'])} | "
                     f"{_number(line['residual_sd'])} |")
    lines += ["", "| depth | median error, flown | worst | with the fits' calibration parts "
              "taken out: median | worst |", "|---|---:|---:|---:|---:|"]
    for depth, errors in fit["end_error_m"].items():
        flown, left = errors["flown"], errors["calibration_taken_out"]
        lines.append(f"| {depth} | {flown['median']:.2f} m | {flown['worst']:.2f} m | "
                     f"{left['median']:.2f} m | {left['worst']:.2f} m |")
    return "\n".join(lines) + "\n"


def _number(value, sign: str = "") -> str:
    return "—" if value is None else f"{value:{sign}.3f}"
