"""Exact feature tracks for a simulated flight: is a VINS error the tracker's or the estimator's?

``companion sim fly --tracks truth`` (docs/vins.md, "The hallway's drift, taken apart") keeps
the front-end as it runs, so every track is born, kept and lost where the tracker has it, and
replaces each track's pixel by the true projection of the point it was born on:

- at birth, the point is the tracker's pixel back-projected to the renderer's depth there,
  through the true camera pose ``T_L_C = truth_pose @ T_B_C``;
- in every later frame, its pixel is ``K [x/z, y/z]`` of that point in the frame's true camera.

A track born on a depth edge (its 3x3 pixels' depths not within 5 % of each other: a corner
between two surfaces belongs to neither) or where nothing was rendered is dropped, as is one
whose point has gone behind the camera or out of the image. The camera must be the one the
renderer drew, exactly: the ideal profile's (the realistic profile's lens, mounting error and
late stamps would make the "truth" wrong), which the caller checks.

Two more sources (``--tracks early-error`` and ``late-error``) keep one part of the tracker's
own error, split at a track's :data:`ERROR_SPLIT_AGE`-th frame, about when it can first be a
landmark: with ``early-error`` a track is the tracker's up to that frame and from then on moves
exactly as its point, ``truth + (tracker_split - truth_split)``, so it keeps the error it
gathered in its first frames, before it could be triangulated (at its birth it has none: its
point is the one under the tracker's pixel); with ``late-error`` it is the truth up
to that frame and from then on moves as the tracker moved it, ``truth_split + (tracker -
tracker_split)``, so it carries only what the tracker gathers while the track is a landmark
(docs/vins.md, "The hallway open loop").
"""

from __future__ import annotations

import dataclasses

import numpy as np

from autonomy.geometry import PinholeCamera, invert_pose
from autonomy.messages import Frame
from autonomy.vins import Tracks

#: Largest spread of the rendered depths around a pixel a track may be born on, as a share of
#: the depth there.
DEPTH_EDGE = 0.05

#: Nearest a point may be in front of the camera, metres.
MIN_DEPTH = 0.1

#: Where ``early-error`` and ``late-error`` split a track's error (module docstring), its age
#: in frames: a landmark needs three keyframes, which come every other frame or so (keyframes
#: at about 10 Hz on a 20 Hz camera), so this is about when it can first be triangulated.
ERROR_SPLIT_AGE = 6

#: The truth's tracks with none, the early or the late part of the tracker's error (module
#: docstring).
TRUTH_SOURCES = ("truth", "early-error", "late-error")

#: The feature tracks a simulated VINS can run on: the tracker's, or one of the truth's.
TRACK_SOURCES = ("tracker", *TRUTH_SOURCES)


def replacement_for(source: str, camera: PinholeCamera, T_B_C) -> TruthTracks | None:
    """The replacement of the tracks that ``source`` (one of :data:`TRACK_SOURCES`) names, or
    None for the tracker's own; ValueError naming the choices for any other."""
    if source not in TRACK_SOURCES:
        raise ValueError(f"tracks must be one of {', '.join(TRACK_SOURCES)}, got {source!r}")
    return None if source == "tracker" else TruthTracks(camera, T_B_C, source)


class TruthTracks:
    """Replaces the tracks of each frame by the true projections of their points, with the
    part of the tracker's error that ``source`` keeps (module docstring); one instance per
    flight, fed every frame in order."""

    def __init__(self, camera: PinholeCamera, T_B_C, source: str = "truth"):
        if source not in TRUTH_SOURCES:
            raise ValueError(f"truth tracks' source must be one of {', '.join(TRUTH_SOURCES)}, "
                             f"got {source!r}")
        self.camera = camera
        self.T_B_C = np.asarray(T_B_C, dtype=float)
        self.source = source
        self._points_L: dict[int, np.ndarray] = {}
        #: each track's tracker and true pixel at its split (both sources with an error)
        self._split: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, frame: Frame, tracks: Tracks) -> Tracks:
        """``tracks`` of ``frame`` (which must carry ``truth_pose`` and ``truth_depth``) with
        every pixel the truth's, or the truth's with the part of the tracker's error the source
        keeps, less the tracks that have none."""
        if frame.truth_pose is None or frame.truth_depth is None:
            raise ValueError("truth tracks need the simulator's true pose and depth with "
                             "every frame")
        T_L_C = frame.truth_pose @ self.T_B_C
        born = tracks.ages == 1
        for key, pixel in zip(tracks.ids[born], tracks.pixels[born]):
            point = self._back_project(pixel, frame.truth_depth, T_L_C)
            if point is not None:
                self._points_L[int(key)] = point
        known = np.array([int(key) in self._points_L for key in tracks.ids], dtype=bool)
        points_L = np.array([self._points_L[int(key)] for key in tracks.ids[known]])
        normalised, pixels, visible = self._project(points_L.reshape(-1, 3), T_L_C)
        keep = np.flatnonzero(known)[visible]
        # ids are never reused: a track gone from this frame is gone for good
        self._points_L = {int(key): self._points_L[int(key)] for key in tracks.ids[known]}
        self._split = {key: split for key, split in self._split.items()
                       if key in self._points_L}
        if self.source != "truth":  # split where the point is out of view too: it may return
            pixels = self._with_tracker_error(tracks.ids[known], tracks.ages[known],
                                              tracks.pixels[known], pixels)
            normalised = (pixels - (self.camera.cx, self.camera.cy)) / (self.camera.fx,
                                                                         self.camera.fy)
        pixels, normalised = pixels[visible], normalised[visible]
        scale = None if tracks.noise_scale is None else tracks.noise_scale[keep]
        return dataclasses.replace(tracks, ids=tracks.ids[keep], pixels=pixels,
                                   normalised=normalised, ages=tracks.ages[keep],
                                   noise_scale=scale)

    def _with_tracker_error(self, ids, ages, tracker: np.ndarray,
                            truth: np.ndarray) -> np.ndarray:
        """The pixels of ``early-error`` or ``late-error`` tracks (module docstring) from the
        tracker's and the true ones, each (N, 2) in the order of ``ids``. The split follows a
        track up to its :data:`ERROR_SPLIT_AGE`-th frame (a track first seen older, which a
        replacement fed from the tracks' births never meets, splits where it is first seen)."""
        early = self.source == "early-error"
        pixels = np.array(tracker if early else truth, dtype=float)
        for row, (key, age) in enumerate(zip(ids.tolist(), ages.tolist())):
            if age <= ERROR_SPLIT_AGE:
                self._split[key] = (tracker[row].copy(), truth[row].copy())
                continue
            tracker_then, truth_then = self._split.setdefault(key, (tracker[row], truth[row]))
            pixels[row] = (truth[row] + tracker_then - truth_then if early
                           else truth_then + tracker[row] - tracker_then)
        return pixels

    def _back_project(self, pixel, depth: np.ndarray, T_L_C: np.ndarray) -> np.ndarray | None:
        c = self.camera
        u, v = (int(round(float(x))) for x in pixel)
        if not (1 <= u < depth.shape[1] - 1 and 1 <= v < depth.shape[0] - 1):
            return None
        around = depth[v - 1:v + 2, u - 1:u + 2]
        z = float(depth[v, u])
        if not (np.isfinite(around).all() and around.max() - around.min() <= DEPTH_EDGE * z):
            return None
        p_C = np.array([(pixel[0] - c.cx) / c.fx * z, (pixel[1] - c.cy) / c.fy * z, z])
        return T_L_C[:3, :3] @ p_C + T_L_C[:3, 3]

    def _project(self, points_L: np.ndarray, T_L_C: np.ndarray):
        """Normalised coordinates, pixels and whether each point is in front of the camera
        and inside the image."""
        c = self.camera
        T_C_L = invert_pose(T_L_C)
        p_C = points_L @ T_C_L[:3, :3].T + T_C_L[:3, 3]
        in_front = p_C[:, 2] > MIN_DEPTH
        with np.errstate(divide="ignore", invalid="ignore"):
            normalised = p_C[:, :2] / p_C[:, 2:]
        pixels = normalised * (c.fx, c.fy) + (c.cx, c.cy)
        inside = ((pixels[:, 0] >= -0.5) & (pixels[:, 0] <= c.width - 0.5)
                  & (pixels[:, 1] >= -0.5) & (pixels[:, 1] <= c.height - 0.5))
        return normalised, pixels, in_front & inside
