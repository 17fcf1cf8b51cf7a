"""Traffic: the SOTIF cut-out scenario and randomised training scenes.

SOTIF scenario (Patel & Jung 2024): the ego drives in lane 3 at 90 km/h behind a fast car
(ACC gap keeping); a slow car drives at 60 km/h ahead in the same lane. The fast car changes to
lane 4 and leaves the slow car's lane 10 m (bumper to bumper) behind it: its lane change starts
early enough that its body is clear of the slow car's (``CLEARANCE_M`` apart sideways) when the
gap is down to ``trigger_gap``, so the two never touch whatever the closing speed. The ego's ACC
then takes the slow car as its target and decelerates. 10 Hz simulation, every 5th step recorded
(scenario sets record every step through the decision window).

Training scenes never reproduce it: they are independent snapshots of random traffic (their
own random streams and world clutter), not the scripted cut-out with its fixed cars.
The braking rule of the decision window is the floor's (``harness.core.braking``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from harness.core.braking import A_PASS_MPS2, EGO_DIMS, T_REACT_SYSTEM_S, stopping_distance
from harness.core.visibility import footprint_shares
from simulator.labels import lidar_boxes
from simulator.lidar import Pose
from simulator.road import RoadConfig, lane_center, road_to_world
from simulator.vehicles import Vehicle, sample_body, sample_dims, sample_paint


@dataclass(frozen=True)
class SotifConfig:
    ego_lane: int = 3
    ego_speed: float = 25.0  # m/s (90 km/h)
    slow_speed: float = 60.0 / 3.6  # m/s
    trigger_gap: float = 10.0  # m bumper to bumper, fast car behind slow car, when the fast car clears its lane
    lane_change_duration: float = 3.5  # s
    time_to_trigger: float = 1.0  # s after the first recorded frame
    start_s: float = 140.0  # m, ego position at t = 0
    dt: float = 0.1  # s
    record_every: int = 5
    acc_time_gap: float = 2.0  # s
    acc_standstill: float = 4.0  # m
    slow_body: tuple = ("sedan", (4.75, 1.83, 1.45), "silver")
    fast_body: tuple = ("hatchback", (4.15, 1.78, 1.50), "red")


@dataclass
class FrameState:
    pose: Pose
    ego_speed: float
    vehicles: list[Vehicle]
    time_s: float
    info: dict = field(default_factory=dict)


def _vehicle(cfg: RoadConfig, body: str, dims, paint: str, s: float, d: float, speed: float,
             dd_ds: float = 0.0, role: str = "traffic", oncoming: bool = False,
             reflectance: float | None = None) -> Vehicle:
    x, y, h = road_to_world(cfg, np.array(s), np.array(d))
    heading = float(h) + math.atan(dd_ds) + (math.pi if oncoming else 0.0)
    return Vehicle(body, tuple(float(v) for v in dims), paint, float(x), float(y), heading, speed, role, reflectance)


def _acc(gap: float, v: float, v_lead: float, sc: SotifConfig) -> float:
    """ACC acceleration (m/s^2): gap keeping to standstill + time_gap * v."""
    desired = sc.acc_standstill + sc.acc_time_gap * v
    return float(np.clip(0.2 * (gap - desired) + 0.9 * (v_lead - v), -6.0, 1.5))


VISIBLE_LEAD_S = 0.5  # s recorded at 10 Hz before the slow vehicle is first visible (the confirmation rule's window)
CLEARANCE_M = 0.25  # m side to side between the fast car and the slow car when the fast car is out of its way


def _quintic(tau: float) -> tuple[float, float]:
    """Smooth 0 -> 1 lane-change profile and its derivative in tau."""
    tau = min(max(tau, 0.0), 1.0)
    return 10 * tau**3 - 15 * tau**4 + 6 * tau**5, 30 * tau**2 - 60 * tau**3 + 30 * tau**4


def clear_time_s(sc: SotifConfig, lane_width: float, slow_offset: float = 0.0) -> float:
    """Seconds from the start of the fast car's lane change until its body is ``CLEARANCE_M`` to the side of
    the slow car's (the slow car ``slow_offset`` m left of its lane centre; the fast car moves left by one
    ``lane_width`` along the quintic profile)."""
    need = (slow_offset + (sc.fast_body[1][1] + sc.slow_body[1][1]) / 2 + CLEARANCE_M) / lane_width
    if need >= 1.0:
        raise ValueError(f"the fast car cannot clear a slow car {slow_offset} m off its lane centre in a "
                         f"{lane_width} m lane")
    lo, hi = 0.0, 1.0
    for _ in range(60):  # the profile rises monotonically over [0, 1]
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if _quintic(mid)[0] < need else (lo, mid)
    return hi * sc.lane_change_duration


def _background(sc: SotifConfig, rng: np.random.Generator) -> list[tuple]:
    """(body, dims, paint, s0, lane, speed, oncoming) of the other traffic, fixed per seed."""
    out = [("truck", sample_dims("truck", rng), "white", sc.start_s + rng.uniform(15, 35), 1, 22.0, False),
           (sample_body(rng), None, sample_paint(rng), sc.start_s + rng.uniform(60, 90), 2, 26.5, False)]
    for k in range(4):
        out.append((sample_body(rng), None, sample_paint(rng), sc.start_s + 80 + 90 * k + rng.uniform(0, 40),
                    int(rng.integers(1, 5)), float(rng.uniform(24, 33)), True))
    return [(b, d if d is not None else sample_dims(b, rng), p, s, ln, v, onc) for b, d, p, s, ln, v, onc in out]


def sotif_run(road: RoadConfig, frames: int, rng: np.random.Generator, sc: SotifConfig = SotifConfig(),
              slow_offset: float = 0.0, slow_reflectance: float | None = None) -> list[FrameState]:
    """Recorded frames of the scenario (deterministic given rng's background traffic). ``slow_offset``:
    the slow car's lateral offset in its lane (m, left +); ``slow_reflectance``: its paint's 905 nm
    reflectance for the LiDAR (None: the paint table's)."""
    l_s, l_f = sc.slow_body[1][0], sc.fast_body[1][0]
    d3, d4 = lane_center(road, sc.ego_lane), lane_center(road, sc.ego_lane + 1)
    gap0 = sc.acc_standstill + sc.acc_time_gap * sc.ego_speed
    s_e, v_e = sc.start_s, sc.ego_speed
    s_f = s_e + gap0 + (EGO_DIMS[0] + l_f) / 2
    # the gap at which the lane change starts: trigger_gap once the fast car is clear of the slow car
    t_clear = clear_time_s(sc, d4 - d3, slow_offset)
    start_gap = sc.trigger_gap + (sc.ego_speed - sc.slow_speed) * t_clear
    s_s = s_f + (l_f + l_s) / 2 + start_gap + (sc.ego_speed - sc.slow_speed) * sc.time_to_trigger
    bg = _background(sc, rng)
    t_lc = None
    out = []
    for step in range(frames * sc.record_every):
        t = step * sc.dt
        if t_lc is None and s_s - s_f - (l_s + l_f) / 2 <= start_gap + 1e-9:
            t_lc = t
        lam, dlam = _quintic((t - t_lc) / sc.lane_change_duration) if t_lc is not None else (0.0, 0.0)
        d_f = d3 + (d4 - d3) * lam
        slope_f = (d4 - d3) * dlam / (sc.lane_change_duration * sc.ego_speed)
        fast_in_lane = abs(d_f - d3) < road.lane_width / 2
        lead_s, lead_l, lead_v = (s_f, l_f, sc.ego_speed) if fast_in_lane else (s_s, l_s, sc.slow_speed)
        if step % sc.record_every == 0:
            out.append(_sotif_frame(road, sc, t, s_e, v_e, (s_f, d_f, slope_f), (s_s, slow_offset, slow_reflectance),
                                    bg))
        a = _acc(lead_s - s_e - (lead_l + EGO_DIMS[0]) / 2, v_e, lead_v, sc)
        v_e = max(0.0, v_e + a * sc.dt)
        s_e += v_e * sc.dt
        s_f += sc.ego_speed * sc.dt
        s_s += sc.slow_speed * sc.dt
    for st in out:
        st.info["lane_change_time_s"] = float("nan") if t_lc is None else t_lc
        st.info["cutout_time_s"] = float("nan") if t_lc is None else t_lc + t_clear
    return out


def _sotif_frame(road, sc, t, s_e, v_e, fast: tuple, slow: tuple, bg) -> FrameState:
    """fast = (s, d, dd/ds), slow = (s, lateral offset, reflectance or None) of the two scripted cars."""
    (s_f, d_f, slope_f), (s_s, off_s, refl_s) = fast, slow
    d3 = lane_center(road, sc.ego_lane)
    x, y, h = road_to_world(road, np.array(s_e), np.array(d3))
    pose = Pose(float(x), float(y), float(h))
    vs = [_vehicle(road, *sc.slow_body, s_s, d3 + off_s, sc.slow_speed, role="slow", reflectance=refl_s),
          _vehicle(road, *sc.fast_body, s_f, d_f, sc.ego_speed, slope_f, role="fast")]
    for body, dims, paint, s0, lane, speed, onc in bg:
        s = s0 - speed * t if onc else s0 + speed * t
        vs.append(_vehicle(road, body, dims, paint, s, lane_center(road, lane, onc), speed, oncoming=onc))
    info = {"slow_car_speed_mps": sc.slow_speed, "slow_car_distance_m": float(s_s - s_e)}
    return FrameState(pose, v_e, vs, t, info)


def window_length_s(gap_m: float, closing_mps: float, t_react: float = T_REACT_SYSTEM_S,
                    decel: float = A_PASS_MPS2) -> float:
    """Seconds from the lane change until a gap of gap_m (m), closing at closing_mps (held), is down to the
    stopping distance with reaction time t_react and deceleration decel: the latest moment the obstacle can be
    confirmed and still pass (by default the verdict's most lenient criterion, an automated system's reaction
    and 6 m/s^2). 0 when it already is; inf when the ego does not close in."""
    if closing_mps <= 0:
        return math.inf
    return max(gap_m - stopping_distance(closing_mps, t_react, decel), 0.0) / closing_mps


def first_visible_step(states: list[FrameState], start: int, stop: int) -> int | None:
    """The first step in [start, stop] at which any of the slow vehicle's (``states[k].vehicles[0]``) BEV footprint
    is unoccluded by the other vehicles and within the detectors' range, seen from the LiDAR
    (``harness.core.visibility``: the reference's geometry); None when it never is."""
    for k in range(start, min(stop, len(states) - 1) + 1):
        st = states[k]
        boxes = lidar_boxes(st.vehicles, st.pose, 0.0)
        if footprint_shares(boxes[0], boxes[1:])["visible"] > 0.0:
            return k
    return None


def instance_steps(states: list[FrameState], sc: SotifConfig, lead_in: int, slack_s: float,
                   window_max_s: float) -> list[tuple[int, bool]]:
    """(step, in the decision window) of the frames an instance records, from its run at every step (states[k] at
    step k). The decision window runs from the lane change through the latest confirmation that can still pass
    (window_length_s of the gap, front bumper to rear face, and the closing speed at the lane change) plus
    ``slack_s``, at most ``window_max_s`` after the cut-out (the fast car clear of the slow car). It is recorded at
    every step (the LiDAR's 10 Hz) from ``VISIBLE_LEAD_S`` before the slow vehicle is first visible at all (no
    detector can hit it earlier; the reference needs 30 % of it), or from the lane change when that is later or it
    never is; ``lead_in`` frames every ``sc.record_every``-th step come before."""
    step_lc = int(round(states[0].info["lane_change_time_s"] / sc.dt))
    st = states[step_lc]
    gap = st.info["slow_car_distance_m"] - (sc.slow_body[1][0] + EGO_DIMS[0]) / 2
    clear_s = states[0].info["cutout_time_s"] - states[0].info["lane_change_time_s"]
    end_s = min(window_length_s(gap, st.ego_speed - sc.slow_speed) + slack_s, clear_s + window_max_s)
    last = step_lc + int(round(end_s / sc.dt))
    seen = first_visible_step(states, step_lc, last)
    first = step_lc if seen is None else max(step_lc, seen - int(round(VISIBLE_LEAD_S / sc.dt)))
    lead = [(first - k * sc.record_every, False) for k in range(lead_in, 0, -1) if first >= k * sc.record_every]
    return lead + [(k, True) for k in range(first, last + 1)]


def run_steps(sc: SotifConfig, window_max_s: float, slack_s: float) -> int:
    """Steps an instance's run needs (every step simulated): to its lane change, its cut-out (at most the whole
    lane change), its longest window and slack."""
    return int(math.ceil((sc.time_to_trigger + sc.lane_change_duration + window_max_s + slack_s) / sc.dt)) + 2


@dataclass(frozen=True)
class TrainConfig:
    density_range: tuple[float, float] = (0.8, 2.5)  # vehicles per 100 m and lane
    ahead: float = 95.0  # m, farthest vehicle placed ahead of the ego
    behind: float = 45.0  # m
    lane_change_share: float = 0.12
    truck_share: float = 0.1
    van_share: float = 0.1


def _free(spans: list, s0: float, s1: float, d0: float, d1: float) -> bool:
    return all(s1 + 1.0 < a or s0 - 1.0 > b or d1 + 0.3 < c or d0 - 0.3 > e for a, b, c, e in spans)


def training_scene(road: RoadConfig, rng: np.random.Generator, tc: TrainConfig = TrainConfig()) -> FrameState:
    """A random highway traffic snapshot around a randomly placed ego."""
    ego_lane = int(rng.integers(1, road.lanes + 1))
    s_e = float(rng.uniform(80.0, road.length - 250.0))
    v_e = float(rng.uniform(20.0, 36.0))
    d_e = lane_center(road, ego_lane)
    x, y, h = road_to_world(road, np.array(s_e), np.array(d_e))
    spans = [(s_e - EGO_DIMS[0] / 2, s_e + EGO_DIMS[0] / 2, d_e - 1.0, d_e + 1.0)]
    vehicles = []
    dens = rng.uniform(*tc.density_range)
    for onc in (False, True):
        for lane in range(1, road.lanes + 1):
            lane_dens = dens * rng.uniform(0.5, 1.5) * (0.6 if onc else 1.0)
            s = s_e - tc.behind - rng.uniform(0.0, 100.0 / lane_dens)
            while True:
                s += 6.0 + rng.exponential(100.0 / lane_dens)
                if s > s_e + tc.ahead:
                    break
                if s < s_e - tc.behind:
                    continue
                v = _train_vehicle(road, rng, tc, s, lane, onc, spans)
                if v is not None:
                    vehicles.append(v)
    return FrameState(Pose(float(x), float(y), float(h)), v_e, vehicles, 0.0,
                      {"slow_car_speed_mps": float("nan"), "slow_car_distance_m": float("nan"),
                       "lane_change_time_s": float("nan")})


def _train_vehicle(road, rng, tc, s, lane, onc, spans) -> Vehicle | None:
    body = sample_body(rng, tc.truck_share if lane <= 2 else 0.02, tc.van_share)
    dims = sample_dims(body, rng)
    d = lane_center(road, lane, onc) + rng.uniform(-0.3, 0.3)
    slope = 0.0
    if rng.random() < tc.lane_change_share and body != "truck":
        other = lane + (1 if lane < road.lanes and (lane == 1 or rng.random() < 0.5) else -1)
        frac = rng.uniform(0.2, 0.8)
        d = d + (lane_center(road, other, onc) - lane_center(road, lane, onc)) * frac
        slope = np.sign(lane_center(road, other, onc) - d) * rng.uniform(0.03, 0.08)
    half_w = dims[1] / 2 + abs(slope) * dims[0] / 2
    if not _free(spans, s - dims[0] / 2, s + dims[0] / 2, d - half_w, d + half_w):
        return None
    spans.append((s - dims[0] / 2, s + dims[0] / 2, d - half_w, d + half_w))
    speed = float(rng.uniform(21.0, 25.0) if body == "truck" else rng.uniform(24.0, 40.0))
    return _vehicle(road, body, dims, sample_paint(rng), s, d, speed, -slope if onc else slope, oncoming=onc)
