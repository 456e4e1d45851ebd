"""`companion bench rescale` runs the real rescaler and reports what the README promises.

Only the shape of the report is asserted here; the speed itself is measured, not asserted
(docs/benchmarks.md keeps the numbers).
"""

import json
import subprocess
import sys

import numpy as np

from autonomy.depth.rescale import METHODS, fit
from companion.tools.bench import synthetic_scene


def bench(*args):
    return subprocess.run([sys.executable, "-m", "companion", "bench", "rescale", *args],
                          capture_output=True, text=True, timeout=300)


def test_json_report_has_every_method_with_three_positive_timings():
    run = bench("--json", "--repeats", "2", "--size", "48x64", "--anchors", "60")
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout)
    assert report["anchors"] == 60 and report["image"] == [48, 64]
    assert list(report["methods"]) == list(METHODS)
    for timings in report["methods"].values():
        assert set(timings) == {"fit_ms", "depth_ms", "direct_ms"}
        assert all(value > 0 for value in timings.values())


def test_table_report_names_every_method():
    run = bench("--repeats", "1", "--size", "24x32", "--anchors", "40")
    assert run.returncode == 0, run.stderr
    for method in METHODS:
        assert method in run.stdout


def test_config_overrides_reach_the_benchmark_and_a_failure_is_reported_plainly():
    run = bench("--repeats", "1", "--size", "24x32", "--anchors", "40",
                "--set", "rescale.min_anchors=100")
    assert run.returncode == 1
    assert "found no fit on the benchmark scene: 40 valid anchors, need 100" in run.stderr
    assert "Traceback" not in run.stderr


def test_more_anchors_than_pixels_is_refused():
    run = bench("--repeats", "1", "--size", "4x4", "--anchors", "17")
    assert run.returncode == 1
    assert "cannot place 17 anchors in a 4x4 image" in run.stderr


def test_benchmark_scene_is_fitted_well_by_the_default_method():
    scene = synthetic_scene((120, 160), 150)
    model = fit(scene.anchor_disparity, scene.anchor_depth)
    assert model.ok
    assert model.anchors.outliers >= 5  # the scene's 5 % gross outliers were found
    depth = model.depth(scene.relative_disparity)
    assert np.isfinite(depth).all()
