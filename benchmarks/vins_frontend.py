"""Speed of the VINS front-end on one core: median milliseconds per 640x480 frame.

    python benchmarks/vins_frontend.py [--frames 95] [--skip 0] [--dataset DIR]

Feeds the EuRoC V1_01 cam0 images, or any recording in EuRoC's folder format (``--dataset``: a
``companion sim record`` flight, ``--skip`` its take-off to time its cruise), cropped to their
central 640x480 (principal point moved to match), through FeatureTracker.track with
cv2.setNumThreads(1). Baseline in the same run:
goodFeaturesToTrack alone (150 corners, 30 px apart) on the same frames, and, interleaved
on the same frames, the default tracker with the affine refinement of its tracks
(``affine_refinement``), with anchored tracks (``anchor_age = 2``, under the affine map and
under a homography, ``anchor_warp``; the latter also with each track's noise from its
texture, ``texture_weights``, and with a track ended where its anchor is given up,
``anchor_given_up = "end"``) and the tracker of before
2026-11-28 (VINS-Mono's 21 px Lucas-Kanade window, no second try on a deeper pyramid;
docs/vins.md); for the anchored trackers also the anchors given up per frame. Prints one JSON
object.
"""

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from autonomy.vins import FeatureTracker, FrontendOptions
from drivers.dataset.euroc import read_camera

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "euroc_v1_01"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=95)
    parser.add_argument("--dataset", type=Path, default=DEFAULT)
    parser.add_argument("--skip", type=int, default=0, help="frames skipped first (a "
                        "recording's take-off, to time its cruise)")
    args = parser.parse_args()
    if args.skip < 0 or args.frames < 2:
        parser.error(f"--skip must be 0 or more and --frames 2 or more, got {args.skip} and "
                     f"{args.frames}")
    cv2.setNumThreads(1)
    stream = read_camera(args.dataset)
    x0 = (stream.camera.width - 640) // 2
    y0 = (stream.camera.height - 480) // 2
    camera = replace(stream.camera, width=640, height=480, cx=stream.camera.cx - x0,
                     cy=stream.camera.cy - y0)
    frames = [np.ascontiguousarray(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)[y0:y0 + 480, x0:x0 + 640])
              for p in stream.paths[args.skip:args.skip + args.frames]]
    if len(frames) < 2:
        parser.error(f"{args.dataset} has {len(stream.paths)} frames: none to time after "
                     f"--skip {args.skip}")
    tracker = FeatureTracker(camera, stream.distortion)
    variants = {
        "affine": FeatureTracker(camera, stream.distortion,
                                 FrontendOptions(affine_refinement=True)),
        "anchored": FeatureTracker(camera, stream.distortion, FrontendOptions(anchor_age=2)),
        "anchored_homography": FeatureTracker(
            camera, stream.distortion, FrontendOptions(anchor_age=2, anchor_warp="homography")),
        "anchored_homography_texture_weights": FeatureTracker(
            camera, stream.distortion, FrontendOptions(anchor_age=2, anchor_warp="homography",
                                                       texture_weights=True)),
        "anchored_homography_ended": FeatureTracker(
            camera, stream.distortion, FrontendOptions(anchor_age=2, anchor_warp="homography",
                                                       anchor_given_up="end")),
        "lk21": FeatureTracker(camera, stream.distortion,
                               FrontendOptions(lk_window=21, retry_pyramid_levels=0)),
    }
    for each in (tracker, *variants.values()):
        each.track(frames[0])  # warm-up: first-call allocations
    track_ms, gftt_ms, counts, detected = [], [], [], 0
    variant_ms = {name: [] for name in variants}
    given_up = {name: 0 for name in variants}
    for frame in frames[1:]:
        t0 = time.perf_counter()
        tracks = tracker.track(frame)
        t1 = time.perf_counter()
        cv2.goodFeaturesToTrack(frame, 150, 0.01, 30)
        track_ms.append((t1 - t0) * 1e3)
        gftt_ms.append((time.perf_counter() - t1) * 1e3)
        for name, variant in variants.items():
            start = time.perf_counter()
            given_up[name] += variant.track(frame).reanchored
            variant_ms[name].append((time.perf_counter() - start) * 1e3)
        counts.append(len(tracks))
        detected += tracks.detected
    print(json.dumps({"image": [480, 640], "frames": len(track_ms), "threads": 1,
                      "track_ms_median": round(float(np.median(track_ms)), 3),
                      "track_ms_p95": round(float(np.percentile(track_ms, 95)), 3),
                      "gftt_only_ms_median": round(float(np.median(gftt_ms)), 3),
                      **{f"track_{name}_ms_median": round(float(np.median(times)), 3)
                         for name, times in variant_ms.items()},
                      **{f"{name}_given_up_per_frame": round(given_up[name] / len(track_ms), 2)
                         for name in variants if name.startswith("anchored")},
                      "features_median": int(np.median(counts)), "new_features": detected}))


if __name__ == "__main__":
    main()
