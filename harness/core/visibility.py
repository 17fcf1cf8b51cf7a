"""Geometric visibility of a vehicle from the sensor in bird's-eye view: what a reference perception could see.

The slow vehicle's BEV footprint is sampled on a regular grid (``GRID_L`` x ``GRID_W`` cell centres). A sample
is *unoccluded* when the segment from the sensor (the LiDAR frame's origin) to it crosses no other object's
footprint, and *in range* when it lies within the detectors' range (``RANGE_X_M`` ahead, ``RANGE_Y_M``
either side). The vehicle is *perceivable* in a frame when at least ``VISIBLE_MIN`` (30 %) of its
footprint is both. The test is two-dimensional and weather-blind: a roof LiDAR that sees a truck's upper body
over a low car counts it hidden, so the reference is never earlier than what the footprint alone shows.

The simulator uses it too: a scenario instance records at 10 Hz from shortly before any of the slow vehicle is
visible (``simulator.scenario.instance_steps``).

Segment-rectangle crossings are Liang-Barsky clips in each rectangle's own frame, vectorised over samples and
occluders; ``tests/harness/test_visibility.py`` holds them against shapely on random scenes.
"""
from __future__ import annotations

import numpy as np

RANGE_X_M = 80.0  # m ahead: the detectors' range (default profile's point-cloud range, the labelled distance)
RANGE_Y_M = 32.0  # m either side
GRID_L, GRID_W = 12, 5  # footprint samples along the length and the width
VISIBLE_MIN = 0.3  # share of the footprint unoccluded and in range: perceivable


def footprint_samples(box, grid_l: int = GRID_L, grid_w: int = GRID_W) -> np.ndarray:
    """(grid_l * grid_w, 2) BEV points at the cell centres of a grid_l x grid_w split of the box's footprint."""
    b = np.asarray(box, dtype=np.float64).reshape(7)
    u = ((np.arange(grid_l) + 0.5) / grid_l - 0.5) * b[3]
    v = ((np.arange(grid_w) + 0.5) / grid_w - 0.5) * b[4]
    uu, vv = (a.ravel() for a in np.meshgrid(u, v, indexing="ij"))
    c, s = np.cos(b[6]), np.sin(b[6])
    return np.stack([b[0] + uu * c - vv * s, b[1] + uu * s + vv * c], axis=1)


def segments_cross_boxes(ends, boxes) -> np.ndarray:
    """(P, K) bool: the segment from the origin to ends[p] (P, 2) meets the BEV footprint of box k (K, 7)."""
    p = np.asarray(ends, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    if len(p) == 0 or len(b) == 0:
        return np.zeros((len(p), len(b)), dtype=bool)
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    # segment a + t d, t in [0, 1], in each box's frame: a = the origin, d = the end point, both turned by -yaw
    a = np.stack([-b[:, 0] * c - b[:, 1] * s, b[:, 0] * s - b[:, 1] * c], axis=-1)  # (K, 2)
    d = np.stack([p[:, None, 0] * c + p[:, None, 1] * s, -p[:, None, 0] * s + p[:, None, 1] * c], axis=-1)  # (P, K, 2)
    half = b[:, 3:5] / 2  # (K, 2)
    lo, hi = np.zeros(d.shape[:2]), np.ones(d.shape[:2])
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in range(2):
            da, aa, h = d[..., axis], a[None, :, axis], half[None, :, axis]
            t1, t2 = (-h - aa) / da, (h - aa) / da
            parallel = da == 0
            inside = np.abs(aa) <= h
            lo = np.maximum(lo, np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)))
            hi = np.minimum(hi, np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2)))
    return lo <= hi


def unoccluded(samples, occluders) -> np.ndarray:
    """(P,) bool: the sensor's line of sight to each sample (P, 2) crosses no occluder footprint (K, 7)."""
    return ~segments_cross_boxes(samples, occluders).any(axis=1)


def in_range(samples) -> np.ndarray:
    """(P,) bool: the sample lies within the detectors' range."""
    p = np.asarray(samples, dtype=np.float64).reshape(-1, 2)
    return (p[:, 0] >= 0.0) & (p[:, 0] <= RANGE_X_M) & (np.abs(p[:, 1]) <= RANGE_Y_M)


def footprint_shares(box, others) -> dict:
    """Shares of ``box``'s footprint seen from the sensor among the frame's other boxes (K, 7): ``unoccluded``,
    ``in_range`` and ``visible`` (both at once; perceivable when >= ``VISIBLE_MIN``)."""
    pts = footprint_samples(box)
    free, near = unoccluded(pts, others), in_range(pts)
    return {"unoccluded": float(free.mean()), "in_range": float(near.mean()), "visible": float((free & near).mean())}
