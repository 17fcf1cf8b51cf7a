"""Highway geometry: a straight section followed by a gentle left curve.

Road coordinates: s = arc length along the median (m), d = lateral offset, positive to the
left of the driving direction +s. The ego carriageway lies at d < 0 (right-hand traffic),
the oncoming one at d > 0. Lanes are numbered 1 (rightmost) .. lanes (next to the median).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RoadConfig:
    lanes: int = 4
    lane_width: float = 3.5  # m
    straight_length: float = 450.0  # m
    curve_radius: float = 1500.0  # m, left curve
    length: float = 1300.0  # m of road in total
    median_half_width: float = 0.4  # m, concrete barrier half width
    inner_shoulder: float = 0.85  # m between barrier and the fast lane
    hard_shoulder: float = 3.0  # m right of lane 1
    guardrail_gap: float = 0.5  # m between hard shoulder and guardrail

    @property
    def lanes_inner_edge(self) -> float:
        return self.median_half_width + self.inner_shoulder

    @property
    def lanes_outer_edge(self) -> float:
        return self.lanes_inner_edge + self.lanes * self.lane_width

    @property
    def guardrail_offset(self) -> float:
        return self.lanes_outer_edge + self.hard_shoulder + self.guardrail_gap


def lane_center(cfg: RoadConfig, lane: float, oncoming: bool = False) -> float:
    """Lateral offset d of a lane centre (lane may be fractional during lane changes)."""
    d = cfg.lanes_inner_edge + (cfg.lanes - lane + 0.5) * cfg.lane_width
    return d if oncoming else -d


def centreline(cfg: RoadConfig, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World (x, y, heading) of the median at arc lengths s (arrays of the same shape)."""
    s = np.asarray(s, dtype=np.float64)
    s0, r = cfg.straight_length, cfg.curve_radius
    ang = np.maximum(s - s0, 0.0) / r
    x = np.where(s <= s0, s, s0 + r * np.sin(ang))
    y = np.where(s <= s0, 0.0, r * (1.0 - np.cos(ang)))
    return x, y, ang


def road_to_world(cfg: RoadConfig, s: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World (x, y, heading of +s) of road points (s, d)."""
    x, y, h = centreline(cfg, s)
    return x - np.asarray(d) * np.sin(h), y + np.asarray(d) * np.cos(h), h
