"""Where to land after a failsafe: a site ahead that the camera has seen clear to the floor.

PX4's landing descends vertically where it is told to. After a failsafe the vehicle has braked
wherever the failure found it, and the column below that spot was never looked at: the forward
camera sees the floor only from about ``h / tan(vfov / 2)`` ahead (2 m at 1.5 m height with
the simulated camera's 74-degree vertical field), and what it saw of the spot before is gone
from the planner's history by the end of the stop. A spot at flight height can be clear while
the space below it is not: a tripod's legs splay out below its head (docs/results.md: a
realistic sewer flight landed after a mission timeout 0.6 m from a tripod's head, at flight
height beyond its reach, and met a leg at 0.25 m).

So the stop is followed by a short glide to a *landing site*: a point ahead whose column, from
the flight height down to :data:`FLOOR_MARGIN` radii above the floor, every sphere of radius
``r`` along it every :data:`COLUMN_STEP_M`, the depth history judges free (seen, and no
surface within ``r`` of the column's axis above that height), and whose glide at flight
height the planner finds free for the robot's sphere. The candidates lie on a grid ahead
(:data:`SITE_DISTANCES_M` by :data:`SITE_OFFSETS_M`), nearest first. Obstacles lower than the
column's checked bottom (``(FLOOR_MARGIN - 1) r`` on its axis above the floor height given)
and objects the depth misses are not seen: the check is as good as the depth it reads. The
application gives the floor as the body's height at take-off, so the landing gear's height and
the VINS's height drift since widen that unchecked band.
"""

from __future__ import annotations

import math

import numpy as np

SITE_DISTANCES_M = tuple(np.arange(2.0, 8.01, 0.5))
"""Distances ahead of the vehicle of the candidate sites, metres: from where the camera first
sees a column's foot from 1.5 m up, to where it does from about 5.5 m (74-degree vertical
field), within the depth's trusted range (10 m) at a metre's margin."""

SITE_OFFSETS_M = (0.0, -0.5, 0.5, -1.0, 1.0)
"""Sideways offsets of the candidate sites from the heading, metres (positive to the left)."""

COLUMN_STEP_M = 0.25
"""Spacing of the spheres checked down a site's column, metres."""

FLOOR_MARGIN = 1.25
"""The lowest sphere's centre is this many radii above the floor: the depth history's ring
rule reads a surface up to about a quarter radius beyond a sphere as inside it, so a sphere
nearer the floor is never free."""


def candidate_sites(start_W: np.ndarray, heading: float) -> np.ndarray:
    """The candidate sites ``(K, 3)`` at ``start_W``'s height, nearest first (ties: straight
    ahead before aside)."""
    forward = np.array([math.cos(heading), math.sin(heading), 0.0])
    left = np.array([-math.sin(heading), math.cos(heading), 0.0])
    grid = [(math.hypot(d, s), abs(s), d, s) for d in SITE_DISTANCES_M for s in SITE_OFFSETS_M]
    return np.array([start_W + d * forward + s * left for *_, d, s in sorted(grid)])


def column_points(site_W: np.ndarray, floor_z: float, radius: float) -> np.ndarray:
    """Centres ``(M, 3)`` of the spheres of ``radius`` checked down ``site_W``'s column, from
    its height to :data:`FLOOR_MARGIN` radii above ``floor_z``; empty when the site is lower
    than that."""
    bottom = floor_z + FLOOR_MARGIN * radius
    if site_W[2] < bottom:
        return np.zeros((0, 3))
    heights = np.arange(site_W[2], bottom - 1e-9, -COLUMN_STEP_M)
    if heights[-1] > bottom + 1e-9:
        heights = np.append(heights, bottom)
    return np.column_stack([np.full(len(heights), site_W[0]), np.full(len(heights), site_W[1]),
                            heights])
