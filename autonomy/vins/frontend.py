"""The VINS front-end: sparse corners tracked from frame to frame with persistent ids.

The recipe is VINS-Mono's (Qin, Li, Shen, "VINS-Mono", T-RO 2018, feature_tracker.cpp):

1. optional CLAHE on the grey image;
2. pyramidal Lucas-Kanade from the previous frame's features into this one, then back again
   (an 11 px window where VINS-Mono's is 21 px: ``FrontendOptions``); a feature survives
   when both directions converge, it lands inside the image and the round trip returns
   within ``forward_backward_threshold`` pixels of where it started; when fewer than half
   survive this and the RANSAC of step 3, the frame is tracked again on a deeper pyramid
   (``retry_pyramid_levels``: motion beyond the window's reach); with ``affine_refinement``
   (off by default; not VINS-Mono's) each surviving track is then refined under an affine
   warp of its patch (``affine_refine.py``);
3. RANSAC on the fundamental matrix between the two frames' *undistorted* positions, expressed
   as pixels of the camera's ideal pinhole (so the threshold means pixels); with
   ``anchor_age`` (off by default; not VINS-Mono's) each track RANSAC keeps that is that old
   or older is then found against its own patch of the frame it reached that age in, under
   the affine map gathered since, so that it stops gathering each frame's error
   (``anchored_tracks.py``);
4. features are ranked by age; walking from the oldest, each one that is not within
   ``min_distance`` of an older kept feature is kept and masks a disc of that radius;
5. Shi-Tomasi corners fill the unmasked image up to ``max_features``, each with a new id;
6. with ``texture_weights`` (off by default; not VINS-Mono's) each feature is given a position
   noise by how precisely the patch it was born on can be found: the fainter, the more
   (``track_precision.py``).

Ids are integers that increase and are never reused within one tracker. Pixel coordinates
follow OpenCV (pixel centres at integers).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from autonomy.geometry import PinholeCamera, undistort_points
from autonomy.options import OptionError, option, validate
from autonomy.vins.affine_refine import WARP_PARAMETERS, SampledImage, refine_affine
from autonomy.vins.anchored_tracks import Anchors
from autonomy.vins.track_precision import BirthTextures, checked_noise_scale, relative_noise


@dataclass(frozen=True)
class FrontendOptions:
    """How features are detected, tracked and checked (defaults as VINS-Mono's EuRoC config,
    but for Lucas-Kanade's window and its second try)."""

    max_features: int = option(150, ge=1, le=10000, doc="most features tracked at once")
    min_distance: int = option(30, ge=1, le=1000, doc="least distance between features, pixels")
    quality_level: float = option(0.01, gt=0.0, lt=1.0, doc="Shi-Tomasi corner threshold as a "
                                  "share of the strongest corner's response")
    block_size: int = option(3, ge=3, le=31, doc="Shi-Tomasi structure-tensor window, pixels")
    # Not VINS-Mono's 21 px: Lucas-Kanade follows the window's mean motion, and in forward
    # flight the flow grows across a 21 px window, so a track creeps outward frame after
    # frame; the landmarks come out near and the scale shrinks. The small window reaches half
    # as far on each level, so a frame where it keeps fewer than half the tracks is tracked
    # again on a deeper pyramid (docs/vins.md, "The scale's loss was the tracker's window").
    lk_window: int = option(11, ge=3, le=101, doc="Lucas-Kanade window side, pixels (odd)")
    pyramid_levels: int = option(3, ge=1, le=8, doc="Lucas-Kanade pyramid levels including "
                                 "full resolution (OpenCV maxLevel = levels - 1)")
    retry_pyramid_levels: int = option(5, ge=0, le=8, doc="pyramid levels of a second try "
                                       "on a frame where fewer than half the tracks survive "
                                       "pyramid_levels and RANSAC (farther reach for fast "
                                       "motion); 0: none")
    lk_iterations: int = option(30, ge=1, le=1000, doc="most Lucas-Kanade iterations per level")
    lk_epsilon: float = option(0.01, gt=0.0, doc="Lucas-Kanade stops when a step is below "
                               "this, pixels")
    forward_backward_threshold: float = option(1.0, gt=0.0, doc="largest forward-backward "
                                               "round-trip error kept, pixels")
    # Off: it halves the tracks' error, but the flights it scores are not better (docs/vins.md,
    # "Tracks refined under an affine warp") and it doubles the front-end's time.
    affine_refinement: bool = option(False, doc="refine each track under an affine warp of "
                                     "its patch (affine_refine.py: a patch that grows in "
                                     "forward flight biases Lucas-Kanade's translation)")
    # Off: nearer on the ideal camera's navigation benchmark, not on the realistic camera's with
    # its time charged, twice the front-end's (docs/vins.md, "Anchors that converge").
    anchor_age: int = option(0, ge=0, le=1000, doc="from this age on, a track is found "
                             "against its own patch of the frame it reached the age in, "
                             "under the warp gathered since, so it stops gathering "
                             "error (anchored_tracks.py); 0: off")
    anchor_window: int = option(15, ge=5, le=101, doc="side of an anchor's patch, pixels "
                                "(odd)")
    anchor_warp: str = option("affine", choices=tuple(WARP_PARAMETERS), doc="the warp an "
                              "anchor's patch is fitted under: affine, or a homography (a "
                              "wall seen at a slant, which an affine map fits off its centre)")
    anchor_max_shift: float = option(1.0, gt=0.0, doc="an anchor fitting further than this "
                                     "from Lucas-Kanade's answer is given up "
                                     "(anchor_given_up), pixels")
    anchor_max_deformation: float = option(1.0, gt=0.0, doc="an anchor whose warp's "
                                           "derivative at its centre strays further than "
                                           "this from the identity in any entry is given "
                                           "up (anchor_given_up)")
    # "reanchor": restarted or ended, the old tracks' median error falls by a fifth but the
    # flights come out long and no nearer (docs/vins.md, "Tracks whose anchor is given up").
    anchor_given_up: str = option("reanchor", choices=("reanchor", "restart", "end"),
                                  doc="a track whose anchor is given up: anchored again "
                                  "where Lucas-Kanade puts it (reanchor), restarted there as "
                                  "a new track, under a new id (restart), or ended, as Shi "
                                  "and Tomasi's monitoring discards a feature that no longer "
                                  "looks like itself (end)")
    # Off until measured in navigation (docs/vins.md, "Observations weighed by their texture").
    texture_weights: bool = option(False, doc="give each track's observations a noise by how "
                                   "precisely the patch it was born on can be found, the "
                                   "fainter the more (track_precision.py), the frame's "
                                   "median track keeping [vins] pixel_sigma")
    ransac: bool = option(True, doc="reject tracks that break the epipolar geometry "
                          "(fundamental-matrix RANSAC)")
    ransac_threshold: float = option(1.0, gt=0.0, doc="RANSAC epipolar distance limit, "
                                     "undistorted pixels")
    ransac_confidence: float = option(0.99, gt=0.0, lt=1.0, doc="RANSAC confidence")
    border: int = option(1, ge=0, le=100, doc="tracks closer than this to the image edge are "
                         "dropped, pixels")
    clahe: bool = option(False, doc="equalise contrast with CLAHE before tracking")
    clahe_clip_limit: float = option(3.0, gt=0.0, doc="CLAHE contrast limit")
    clahe_tiles: int = option(8, ge=1, le=64, doc="CLAHE tiles along each image side")

    @property
    def fit_window(self) -> int:
        """The side of the patch a track is found by, pixels: an anchor's where tracks are
        anchored, else Lucas-Kanade's window."""
        return self.anchor_window if self.anchor_age else self.lk_window

    def __post_init__(self) -> None:
        validate(self)
        for name in ("lk_window", "anchor_window"):
            if getattr(self, name) % 2 == 0:
                raise OptionError(name, f"must be odd, got {getattr(self, name)}")
        if 0 < self.retry_pyramid_levels <= self.pyramid_levels:
            raise OptionError("retry_pyramid_levels", "must be 0 or more than pyramid_levels "
                              f"({self.pyramid_levels}), got {self.retry_pyramid_levels}")


@dataclass(frozen=True)
class Tracks:
    """The features of one frame, row ``i`` of every array describing feature ``ids[i]``.

    ``ages[i]`` is how many frames the feature has been seen in, this one included (1 for a
    feature detected, or restarted, in this frame). ``pixels`` are distorted image positions,
    ``normalised`` the undistorted ``(X/Z, Y/Z)``. The counters say what happened to the
    previous frame's features: lost by Lucas-Kanade or the forward-backward check (on the
    deeper pyramid's try where that was made), rejected by RANSAC, dropped for crowding
    (closer than ``min_distance`` to an older feature); ``detected`` is the number of new
    features; ``reanchored``, the anchors given up (their tracks kept Lucas-Kanade's answer, to
    be anchored again on this frame where they survive and their patch is usable; restarted or
    ended instead as ``anchor_given_up`` says; 0 without ``anchor_age``). ``noise_scale``, with
    ``texture_weights``, each feature's position noise as a share of the frame's typical
    feature's (``track_precision.py``); None without: every feature alike.
    """

    frame: int
    ids: np.ndarray
    pixels: np.ndarray
    normalised: np.ndarray
    ages: np.ndarray
    lost: int = 0
    rejected: int = 0
    crowded: int = 0
    detected: int = 0
    reanchored: int = 0
    noise_scale: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.noise_scale is not None:
            object.__setattr__(self, "noise_scale",
                               checked_noise_scale(self.noise_scale, len(self.ids)))

    def __len__(self) -> int:
        return len(self.ids)


def fundamental_inliers(camera: PinholeCamera, previous_normalised: np.ndarray,
                        current_normalised: np.ndarray, threshold: float,
                        confidence: float = 0.99) -> np.ndarray:
    """Boolean inlier mask of RANSAC on the fundamental matrix between two views' undistorted
    normalised coordinates, measured in pixels of ``camera``'s focal length.

    Fewer than 8 correspondences, non-finite coordinates or a degenerate fit (OpenCV finds no
    model) keep every finite correspondence: with too little data there is nothing to test.
    """
    a = np.asarray(previous_normalised, dtype=float)
    b = np.asarray(current_normalised, dtype=float)
    finite = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    if finite.sum() < 8:
        return finite
    scale = np.array([camera.fx, camera.fy])
    offset = np.array([camera.cx, camera.cy])
    pa = (a[finite] * scale + offset).astype(np.float32)
    pb = (b[finite] * scale + offset).astype(np.float32)
    try:
        F, mask = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, threshold, confidence)
    except cv2.error:
        return finite
    if F is None or mask is None or F.shape != (3, 3):
        return finite
    inliers = finite.copy()
    inliers[finite] = mask.ravel().astype(bool)
    return inliers


def _gray(image, camera: PinholeCamera) -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise ValueError(f"image must be a numpy array, got {type(image).__name__}")
    if image.size == 0:
        raise ValueError(f"image is empty (shape {image.shape})")
    if image.dtype != np.uint8:
        raise ValueError(f"image must be uint8, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    elif image.ndim != 2:
        raise ValueError(f"image must be (H, W) grey or (H, W, 3) RGB, got shape {image.shape}")
    if image.shape != (camera.height, camera.width):
        raise ValueError(f"image is {image.shape[1]}x{image.shape[0]} but the camera is "
                         f"{camera.width}x{camera.height}")
    return np.ascontiguousarray(image)


class FeatureTracker:
    """Tracks corners through a monocular image sequence; one instance per camera stream."""

    def __init__(self, camera: PinholeCamera, distortion=(), options: FrontendOptions | None = None):
        self.camera = camera
        self.distortion = tuple(float(c) for c in np.asarray(distortion, dtype=float).ravel())
        undistort_points(camera, self.distortion, np.zeros((0, 2)))  # validates the coefficients
        self.options = options or FrontendOptions()
        o = self.options
        self._window = (o.lk_window, o.lk_window)
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, o.lk_iterations,
                          o.lk_epsilon)
        self._clahe = (cv2.createCLAHE(o.clahe_clip_limit, (o.clahe_tiles, o.clahe_tiles))
                       if o.clahe else None)
        self.reset()

    def reset(self) -> None:
        """Forget every track (ids keep increasing, so none is ever reused)."""
        self._previous: np.ndarray | None = None
        self._previous_sampled: SampledImage | None = None  # _previous, for refine_affine
        self._pixels = np.zeros((0, 2), np.float32)
        self._normalised = np.zeros((0, 2))
        self._ids = np.zeros(0, np.int64)
        self._ages = np.zeros(0, np.int64)
        o = self.options
        self._anchors = (Anchors(half=o.anchor_window // 2, max_shift=o.anchor_max_shift,
                                 max_deformation=o.anchor_max_deformation, border=o.border,
                                 warp=o.anchor_warp)
                         if o.anchor_age else None)
        self._birth_textures = (BirthTextures(o.fit_window // 2) if o.texture_weights
                                else None)
        if not hasattr(self, "_next_id"):
            self._next_id = 0
            self._frame = -1

    def _lk(self, prev_image, next_image, points: np.ndarray, levels: int):
        moved, status, _ = cv2.calcOpticalFlowPyrLK(
            prev_image, next_image, points.reshape(-1, 1, 2), None, winSize=self._window,
            maxLevel=levels - 1, criteria=self._criteria)
        return moved.reshape(-1, 2), status.ravel().astype(bool)

    def _follow(self, gray: np.ndarray, points: np.ndarray, levels: int,
                sampled: SampledImage | None):
        """``points`` of the previous image tracked into ``gray`` (``sampled``, the same made
        ready for the affine refinement) on ``levels`` pyramid levels, and whether each is
        kept: both directions converged, it landed inside the border and its round trip came
        back within ``forward_backward_threshold``."""
        o = self.options
        h, w = gray.shape
        forward, ok = self._lk(self._previous, gray, points, levels)
        backward, ok_back = self._lk(gray, self._previous, forward, levels)
        round_trip = np.linalg.norm(backward - points, axis=1)
        keep = ok & ok_back & (round_trip <= o.forward_backward_threshold)
        if o.affine_refinement and keep.any():
            forward[keep], _ = refine_affine(self._previous_sampled, sampled, points[keep],
                                             forward[keep], half=o.lk_window // 2)
        b = o.border  # after the refinement, which may move a track by up to 0.5 px
        inside = ((forward[:, 0] >= b) & (forward[:, 0] <= w - 1 - b)
                  & (forward[:, 1] >= b) & (forward[:, 1] <= h - 1 - b))
        return forward, keep & inside

    def _epipolar(self, previous_normalised: np.ndarray, normalised: np.ndarray,
                  keep: np.ndarray) -> np.ndarray:
        """``keep`` less the tracks RANSAC rejects between the two frames (without RANSAC,
        less those whose undistorted position is not finite)."""
        o, kept = self.options, np.flatnonzero(keep)
        if o.ransac:
            good = fundamental_inliers(self.camera, previous_normalised[kept],
                                       normalised[kept], o.ransac_threshold, o.ransac_confidence)
        else:
            good = np.isfinite(normalised[kept]).all(axis=1)
        judged = np.zeros_like(keep)
        judged[kept[good]] = True
        return judged

    def track(self, image) -> Tracks:
        """Track the previous frame's features into ``image`` (uint8 grey or RGB, the camera's
        size) and top them up with new corners. Raises ValueError on an unusable image."""
        o = self.options
        gray = _gray(image, self.camera)
        if self._clahe is not None:
            gray = self._clahe.apply(gray)
        self._frame += 1
        h, w = gray.shape
        # Made once a frame for the patches fitted with sub-pixel warps, when any are.
        sampled = (SampledImage(gray) if o.affine_refinement or self._anchors is not None
                   else None)
        pixels, ids, ages = self._pixels, self._ids, self._ages
        normalised_prev = self._normalised
        lost = rejected = reanchored = 0
        if len(ids) and self._previous is not None:
            forward, keep = self._follow(gray, pixels, o.pyramid_levels, sampled)
            normalised = undistort_points(self.camera, self.distortion, forward)
            judged = self._epipolar(normalised_prev, normalised, keep)
            if o.retry_pyramid_levels and len(ids) >= 8 and judged.mean() < 0.5:
                # Motion beyond the small window's reach (a frame after a long gap, a jolt):
                # most tracks lost, or converged where RANSAC rejects them. Again, all of
                # them, from a deeper pyramid.
                forward, keep = self._follow(gray, pixels, o.retry_pyramid_levels, sampled)
                normalised = undistort_points(self.camera, self.distortion, forward)
                judged = self._epipolar(normalised_prev, normalised, keep)
            lost, rejected = int((~keep).sum()), int((keep & ~judged).sum())
            if self._anchors is not None:
                self._anchors.keep(judged)
                forward[judged] = self._anchors.follow(sampled, forward[judged])
                reanchored = int(self._anchors.given_up.sum())
                if o.anchor_given_up == "end":
                    judged[np.flatnonzero(judged)[self._anchors.given_up]] = False
                    self._anchors.keep(~self._anchors.given_up)
                normalised[judged] = undistort_points(self.camera, self.distortion,
                                                      forward[judged])
            pixels, ids, ages = forward[judged], ids[judged], ages[judged] + 1
            normalised = normalised[judged]
            if self._anchors is not None and o.anchor_given_up == "restart":
                self._restart(ids, ages, self._anchors.given_up)
        else:
            pixels = np.zeros((0, 2), np.float32)
            ids = np.zeros(0, np.int64)
            ages = np.zeros(0, np.int64)
            normalised = np.zeros((0, 2))

        # Oldest first; each kept feature masks a disc of min_distance (VINS-Mono's setMask).
        mask = np.zeros((h, w), np.uint8)
        b = o.border
        mask[b:h - b, b:w - b] = 255
        order = np.argsort(-ages, kind="stable")
        keep = np.zeros(len(ids), bool)
        centres = np.rint(pixels).astype(np.int64)
        for i in order:
            x, y = centres[i]
            if mask[y, x]:
                keep[i] = True
                cv2.circle(mask, (int(x), int(y)), o.min_distance, 0, -1)
        crowded = int(len(ids) - keep.sum())
        pixels, ids, ages, normalised = pixels[keep], ids[keep], ages[keep], normalised[keep]
        if self._anchors is not None:
            self._anchors.keep(keep)

        wanted = o.max_features - len(ids)
        detected = 0
        if wanted > 0:
            corners = cv2.goodFeaturesToTrack(gray, wanted, o.quality_level, o.min_distance,
                                              mask=mask, blockSize=o.block_size)
            if corners is not None and len(corners):
                new = corners.reshape(-1, 2).astype(np.float32)
                detected = len(new)
                new_ids = np.arange(self._next_id, self._next_id + detected, dtype=np.int64)
                self._next_id += detected
                pixels = np.concatenate([pixels.astype(np.float32), new])
                ids = np.concatenate([ids, new_ids])
                ages = np.concatenate([ages, np.ones(detected, np.int64)])
                normalised = np.concatenate(
                    [normalised, undistort_points(self.camera, self.distortion, new)])
                if self._anchors is not None:
                    self._anchors.extend(detected)
        if self._anchors is not None:
            due = (ages >= o.anchor_age) & ~self._anchors.anchored
            self._anchors.anchor(sampled, pixels, np.flatnonzero(due))

        noise_scale = self._noise_scales(gray, ids, pixels, ages == 1)
        self._previous = gray
        self._previous_sampled = sampled
        self._pixels = np.ascontiguousarray(pixels, dtype=np.float32)
        self._normalised = normalised
        self._ids, self._ages = ids, ages
        return Tracks(frame=self._frame, ids=ids.copy(), pixels=pixels.astype(float),
                      normalised=normalised.copy(), ages=ages.copy(), lost=lost,
                      rejected=rejected, crowded=crowded, detected=detected,
                      reanchored=reanchored, noise_scale=noise_scale)

    def _restart(self, ids: np.ndarray, ages: np.ndarray, rows: np.ndarray) -> None:
        """The tracks of ``rows`` (a mask) made new ones, born in this frame: fresh ids and
        age 1 (in place)."""
        n = int(rows.sum())
        ids[rows] = np.arange(self._next_id, self._next_id + n)
        ages[rows] = 1
        self._next_id += n

    def _noise_scales(self, gray: np.ndarray, ids: np.ndarray, pixels: np.ndarray,
                      born: np.ndarray) -> np.ndarray | None:
        """With ``texture_weights``, each feature's noise relative to the frame's typical one
        by the texture it was born on, over the window it is fitted in (an anchor's where
        tracks are anchored)."""
        if self._birth_textures is None:
            return None
        return relative_noise(self._birth_textures.update(gray, ids, pixels, born))
