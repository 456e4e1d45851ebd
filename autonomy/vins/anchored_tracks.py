"""Tracks found against their own patch of an earlier frame, so that they stop gathering error.

Frame-to-frame Lucas-Kanade adds each frame's error to a track's: the patch it follows is the
previous frame's, itself off by everything gathered so far. Flying forward the patch also grows
every frame, and a translation fitted to a patch that scales errs in the same direction
frame after frame (``affine_refine.py``). A track then drifts off its point by an error that
grows with its age: on the simulator's sewer hallway 0.09 px at 2–4 frames and 0.8 px past 20
(docs/vins.md, "Tracks refined under an affine warp"). It is this error, gathered while the track
is a landmark, that walks the VINS's scale in a cruise: with only the error each track had
by its sixth frame, six hallway recordings keep their ATE within 0.19 % of the distance, with
the tracker's 0.84 % (docs/vins.md, "The hallway open loop").

Shi and Tomasi's remedy ("Good Features to Track", CVPR 1994, section 4: monitoring a feature
against its first appearance under an affine map) is this module's: once a track is
``anchor_age`` frames old its patch in that frame becomes its anchor, and in every later frame
the track is where the anchor fits under the warp gathered since (``affine_refine.fit_warp``,
from Lucas-Kanade's position and the last frame's warp). The error is then the fit's in this
frame, not a sum over frames. A fit that does not converge, lands further than ``max_shift``
from Lucas-Kanade's answer or deforms the patch beyond ``max_deformation`` keeps Lucas-Kanade's
answer (``given_up``), and the tracker anchors the track again on this frame, restarts it
as a new track or ends it (``FrontendOptions.anchor_given_up``): an anchor is given up where
its patch no longer looks like itself (an occlusion, a change of view the warp does not
describe), never followed into a wrong match. Anchored again, a track carries on from
Lucas-Kanade's answer with the offset it had gathered; restarted or ended, its landmark keeps
the observations that agree with each other, as Shi and Tomasi discard a feature whose
dissimilarity grows (docs/vins.md, "Tracks whose anchor is given up").

The warp is the affine map ``u -> c + A u`` or a homography (``warp``). A patch on a wall seen
at a slant grows more on its near side than on its far one as the camera nears it: the view's
second-order term, which an affine map fitted over the patch turns into an offset of its centre
of ``-A E[u u^T] h`` (``h`` the homography's last row, ``E[u u^T]`` the window's second
moment). Flying forward it points outward, frame after frame, and lengthens the VINS's
scale; the homography describes the plane's view exactly (docs/vins.md, "Anchored tracks
under a homography").

Off by default (``FrontendOptions.anchor_age``): on the simulator's ideal camera it brings the
navigation benchmark's VINS error near issue 24's goal; on the realistic camera, with the gyro's
axes as noise, it halves the open loop's median error but flown with its own time charged (it
doubles the front-end's, 2.2 times under a homography) it is no better in navigation than
Lucas-Kanade (docs/vins.md, "Tracks that stop gathering error", "Anchored tracks under a
homography" and "Anchors that converge").
"""

from __future__ import annotations

import numpy as np

from autonomy.vins.affine_refine import (SampledImage, Templates, centre_jacobians, fit_warp,
                                         identity_warps, prepare_templates, warp_parameters)


#: An anchor's fit ends when a step moves its patch's centre less than this, pixels
#: (``fit_warp``'s ``epsilon``; its default, 0.005, before). On the simulator's exact camera
#: (the sewer at 2 m/s) the tracks' error by age was the same with either, within 0.005 px at
#: every age, and the fits end sooner (docs/vins.md, "Anchors that converge").
EPSILON_PX = 0.02


class Anchors:
    """The anchors of a tracker's tracks, row ``i`` for its track ``i``: the anchor patch
    (prepared for ``fit_warp`` under ``warp``, affine or a homography), the warp gathered since
    and whether there is one."""

    def __init__(self, *, half: int, max_shift: float, max_deformation: float, border: int = 0,
                 warp: str = "affine"):
        self.half, self.max_shift, self.max_deformation = half, max_shift, max_deformation
        self.border, self.warp = border, warp
        self._parameters = warp_parameters(warp)
        self._patches = self._none(0)
        self._warps = np.zeros((0, 3, 3))
        self.anchored = np.zeros(0, bool)
        # each row's anchor given up at the last follow(), kept row for row by keep() and extend()
        self.given_up = np.zeros(0, bool)

    def __len__(self) -> int:
        return len(self.anchored)

    def _none(self, n: int) -> Templates:
        """``n`` placeholder patches (not usable)."""
        m, p = (2 * self.half + 1) ** 2, self._parameters
        return Templates(np.zeros((n, m), np.float32), np.zeros(n),
                         np.zeros((n, p, m), np.float32), np.zeros(n, bool))

    def keep(self, rows) -> None:
        """Keep the rows ``rows`` selects (indices or a mask), in that order."""
        self._patches = self._patches.take(rows)
        self._warps = self._warps[rows]
        self.anchored = self.anchored[rows]
        self.given_up = self.given_up[rows]

    def extend(self, n: int) -> None:
        """Add ``n`` rows for new tracks, not anchored."""
        self._patches = Templates.join(self._patches, self._none(n))
        self._warps = np.concatenate([self._warps, identity_warps(np.zeros((n, 2)),
                                                                  half=self.half)])
        self.anchored = np.concatenate([self.anchored, np.zeros(n, bool)])
        self.given_up = np.concatenate([self.given_up, np.zeros(n, bool)])

    def follow(self, gray: SampledImage, found: np.ndarray) -> np.ndarray:
        """``found`` (Lucas-Kanade's positions of the tracks in ``gray``, one per row) with
        each anchored track moved to where its anchor fits; the failed anchors given up, and
        those that fit closer than ``border`` pixels to the image's edge."""
        rows = np.flatnonzero(self.anchored)
        self.given_up = np.zeros(len(self.anchored), bool)
        if not len(rows):
            return found
        centre, warps, converged = fit_warp(self._patches.take(rows), gray, found[rows],
                                            self._warps[rows], half=self.half,
                                            epsilon=EPSILON_PX)
        h, w = gray.shape
        b = self.border
        with np.errstate(invalid="ignore"):  # a lost fit's warp is NaN: not good
            inside = ((centre[:, 0] >= b) & (centre[:, 0] <= w - 1 - b)
                      & (centre[:, 1] >= b) & (centre[:, 1] <= h - 1 - b))
            deformation = np.abs(centre_jacobians(warps, half=self.half)
                                 - np.eye(2)).max(axis=(1, 2))
            good = (converged & inside
                    & (np.linalg.norm(centre - found[rows], axis=1) <= self.max_shift)
                    & (deformation <= self.max_deformation))
        found = found.copy()
        found[rows[good]] = centre[good]
        self._warps[rows[good]] = warps[good]
        self.anchored[rows[~good]] = False
        self.given_up[rows[~good]] = True
        return found

    def anchor(self, gray: SampledImage, pixels: np.ndarray, rows: np.ndarray) -> None:
        """Anchor the tracks of ``rows`` (indices) on ``gray``, at ``pixels`` (one per row
        of the tracker's tracks)."""
        if not len(rows):
            return
        fresh = prepare_templates(gray, pixels[rows], half=self.half, warp=self.warp)
        # The fresh patches appended, then moved into their rows.
        self._patches = Templates.join(self._patches, fresh)
        order = np.arange(len(self.anchored))
        order[rows] = len(self.anchored) + np.arange(len(rows))
        self._patches = self._patches.take(order)
        self._warps[rows] = identity_warps(pixels[rows], half=self.half)
        self.anchored[rows] = fresh.usable
