"""smoothing_spline's FITPACK smoothing factor, and its knots kept only where anchors support them.

    python benchmarks/smoothing_factor.py [--maps 200] [--seed N]

Fits random smooth monotone maps (an affine map plus two soft steps, as in the tests) from
150 anchors with metric-disparity noise σ = 0.003, for several smoothing factors, and prints
one JSON object: per factor, the median and worst over the maps of the largest and of the RMS
error on the anchor range, in units of σ. The noise σ is estimated from the anchors, so with
s = m an underestimate lets FITPACK chase the noise. Each factor is run twice: with every knot
FITPACK placed (``support 0``) and with the knots that leave at least three distinct anchors in
every knot interval (``support 3``, the product's rule: ``curves._ANCHORS_PER_KNOT_INTERVAL``).
"""

import argparse
import json

import numpy as np

from autonomy.depth import curves
from autonomy.depth.rescale import fit

NOISE = 0.003


def random_map(rng):
    a, b = rng.uniform(0.1, 1.0), rng.uniform(0.02, 0.2)
    steps = [(rng.uniform(0, 0.3), rng.uniform(0.4, 1.8), rng.uniform(0.15, 0.6)) for _ in range(2)]
    return lambda x: b + a * x + sum(w / (1 + np.exp(-(x - c) / s)) for w, c, s in steps)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maps", type=int, default=200)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    variants = [(factor, support) for factor in (1.0, 1.5, 2.0) for support in (0, 3)]
    errors = {variant: [] for variant in variants}
    rng = np.random.default_rng(args.seed)
    for _ in range(args.maps):
        mapping = random_map(rng)
        x = rng.uniform(0.2, 2.0, 150)
        z = 1.0 / (mapping(x) + NOISE * rng.standard_normal(150))
        grid = np.linspace(x.min(), x.max(), 400)
        for factor, support in variants:
            curves._ANCHORS_PER_KNOT_INTERVAL = support  # the rule off (0) or as shipped (3)
            model = fit(x, z, "smoothing_spline", smoothing_factor=factor)
            error = np.abs(model.metric_disparity(grid) - mapping(grid)) / NOISE
            errors[factor, support].append((error.max(), np.sqrt(np.mean(error ** 2))))
    report = {}
    for (factor, support), rows in errors.items():
        largest, rms = np.array(rows).T
        report[f"factor {factor:g}, support {support}"] = {
            "max_median": round(float(np.median(largest)), 2),
            "max_worst": round(float(largest.max()), 2),
            "rms_median": round(float(np.median(rms)), 2),
            "rms_worst": round(float(rms.max()), 2)}
    print(json.dumps({"maps": args.maps, "noise": NOISE, "variants": report}))


if __name__ == "__main__":
    main()
