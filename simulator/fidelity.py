"""What the weather did to a scan, measured on the scan itself (one meta row per frame).

- slow_car_returns: points inside the slow car's box grown by 0.15 m (range noise).
- slow_car_smeared: points inside the box grown by 1.5 m but outside the 0.15 m one, and above the
  box's bottom + 0.3 m (not the road): returns displaced from the car.
- air_returns: points nearer than the first surface along their own ray by more than 0.5 m, within
  30 m of the sensor (raindrops, fog, spray, sunlight): phantom returns in the air.
- slow_car_range_m, slow_car_t2: the slow car's range and the two-way transmission T^2 of the
  published extinction models (Marshall-Palmer rain, LiDAR fog) there: the share of its return power
  that gets through.
"""
from __future__ import annotations

import numpy as np

from harness.core.boxes import points_in_boxes
from simulator import effects
from simulator.weather import WeatherPreset, lidar_fog_extinction, rain_rate_mmh

CAR_MARGIN_M, SMEAR_M, ROAD_CLEARANCE_M = 0.15, 1.5, 0.3
AIR_GAP_M, AIR_RANGE_M = 0.5, 30.0
COLUMNS = ("slow_car_returns", "slow_car_smeared", "air_returns", "slow_car_range_m", "slow_car_t2")


def grown(box: np.ndarray, margin: float) -> np.ndarray:
    out = np.asarray(box, dtype=np.float64).copy()
    out[3:6] += 2 * margin
    return out


def car_returns(points: np.ndarray, box: np.ndarray) -> tuple[int, int]:
    """(points on the car, points smeared around it) for a (7,) LiDAR-frame box."""
    on = points_in_boxes(points, grown(box, CAR_MARGIN_M)[None])[:, 0]
    near = points_in_boxes(points, grown(box, SMEAR_M)[None])[:, 0]
    above = points[:, 2] > box[2] - box[5] / 2 + ROAD_CLEARANCE_M
    return int(on.sum()), int((near & ~on & above).sum())


def air_returns(points: np.ndarray, surface_range: np.ndarray) -> int:
    """Points within AIR_RANGE_M that lie more than AIR_GAP_M before the first surface of their ray."""
    r = np.linalg.norm(points[:, :3].astype(np.float64), axis=1)
    return int(((r < AIR_RANGE_M) & (r < surface_range - AIR_GAP_M)).sum())


def frame_fidelity(points: np.ndarray, slow_box: np.ndarray | None, surface_range: np.ndarray,
                   weather: WeatherPreset) -> dict:
    """The COLUMNS of one frame (the slow car's are None without a slow car)."""
    row = dict.fromkeys(COLUMNS)
    row["air_returns"] = air_returns(points, surface_range)
    if slow_box is not None:
        row["slow_car_returns"], row["slow_car_smeared"] = car_returns(points, slow_box)
        r = float(np.linalg.norm(slow_box[:3]))
        a_rain = effects.marshall_palmer_extinction(rain_rate_mmh(weather))
        t2 = effects.two_way_transmission(np.array([r]), a_rain, lidar_fog_extinction(weather), weather.fog_distance)
        row["slow_car_range_m"], row["slow_car_t2"] = round(r, 3), round(float(t2[0]), 5)
    return row
