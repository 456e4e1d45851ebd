"""Cost of rectifying each camera frame (``autonomy.lens.Rectifier``), against a plain copy of
the frame and against ``cv2.undistort``, which builds its maps on every call.

    python benchmarks/rectify.py [--repeats 200] [--threads 0]

One 640x480 RGB uint8 frame of random texture per lens: ``radtan`` with EuRoC cam0's
coefficients (k1 -0.28, k2 0.073, p1 0.0002, p2 1.8e-5) at fx = fy = 458, rectified onto the
same focal length; ``equidistant`` with a RealSense T265's coefficients (farm-ng/tractor's
DefaultFishEyeT265CameraModel) at f = 216 (the T265's 286 scaled to 640 columns), rectified
onto a 100 degree pinhole. Per lens, interleaved medians in milliseconds of:

- ``copy_ms``: ``frame.copy()``, the baseline (touching every byte once);
- ``rectify_ms``: ``Rectifier.__call__``, what ``CalibratedCamera`` does per frame (float32
  maps made once, ``cv2.remap`` bilinear);
- ``remap_fixed_ms``: the same remap with the maps converted once to OpenCV's 16-bit
  fixed-point form (``cv2.convertMaps``), to see what that would save;
- ``undistort_ms``: ``cv2.undistort`` (``cv2.fisheye.undistortImage`` for the fisheye), which
  computes the maps again every call;

and ``maps_ms``, building the ``Rectifier`` (once per camera). ``max_diff`` is the largest
difference, in grey levels, between the Rectifier's frame and OpenCV's own, over the pixels
both fill. ``--threads`` sets OpenCV's thread count (0: its default).
"""

import argparse
import json
import statistics
import time

import cv2
import numpy as np

from autonomy.geometry import PinholeCamera
from autonomy.lens import CameraModel, Rectifier
from companion.tools.bench import interleaved_medians_ms

LENSES = {
    "radtan": (CameraModel(PinholeCamera(640, 480, 458.0, 458.0, 319.5, 239.5), "radtan",
                           (-0.28, 0.073, 0.0002, 1.8e-5)), 0.0),
    "equidistant": (CameraModel(PinholeCamera(640, 480, 216.0, 216.0, 319.5, 239.5),
                                "equidistant", (-0.0080617731437087059, 0.04318523034453392,
                                                -0.039864420890808105, 0.0068964879028499126)),
                    100.0),
}


def measure(model: CameraModel, hfov_deg: float, frame: np.ndarray, repeats: int) -> dict:
    target = model.rectified(hfov_deg)
    K, D, newK = model.pinhole.K, np.array(model.coefficients), target.K
    builds = []
    for _ in range(5):
        start = time.perf_counter()
        rectifier = Rectifier(model, target)
        builds.append(1e3 * (time.perf_counter() - start))
    fixed = cv2.convertMaps(rectifier._map_u, rectifier._map_v, cv2.CV_16SC2)

    if model.distortion == "equidistant":
        def opencv():
            return cv2.fisheye.undistortImage(frame, K, D, Knew=newK)
    else:
        def opencv():
            return cv2.undistort(frame, K, D, None, newK)

    def remap_fixed():
        return cv2.remap(frame, fixed[0], fixed[1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    ours, theirs = rectifier(frame).astype(int), opencv().astype(int)
    both = (ours > 0).all(axis=2) & (theirs > 0).all(axis=2)
    copy_ms, rectify_ms, fixed_ms, undistort_ms = interleaved_medians_ms(
        [frame.copy, lambda: rectifier(frame), remap_fixed, opencv], repeats)
    return {"copy_ms": round(copy_ms, 3), "rectify_ms": round(rectify_ms, 3),
            "remap_fixed_ms": round(fixed_ms, 3), "undistort_ms": round(undistort_ms, 3),
            "rectify_over_copy": round(rectify_ms / copy_ms, 1),
            "undistort_over_rectify": round(undistort_ms / rectify_ms, 1),
            "maps_ms": round(statistics.median(builds), 2),
            "max_diff": int(np.abs(ours - theirs)[both].max())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--threads", type=int, default=0)
    args = parser.parse_args()
    if args.threads:
        cv2.setNumThreads(args.threads)
    frame = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    frame = cv2.GaussianBlur(frame, (0, 0), 2.0)  # texture, not per-pixel noise
    result = {"frame": [480, 640, 3], "opencv_threads": cv2.getNumThreads(),
              "repeats": args.repeats}
    for name, (model, hfov) in LENSES.items():
        result[name] = measure(model, hfov, frame, args.repeats)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
