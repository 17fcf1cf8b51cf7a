"""The braking decision of the SOTIF verdict: confirmation, the frames a detector can process, the outcome.

- *Confirmation*: the obstacle is confirmed at the first hit frame i whose window (t_i - W, t_i] holds at
  least k hits (default 3 within 0.5 s: 3 of 5 frames at the LiDAR's 10 Hz). Frames spaced p apart can hold
  k hits only when W > (k - 1) p, so the window is stretched to k p where the frames are sparser than W / k
  (a detector slower than the sensor, or a set recorded at 2 Hz): ``confirm_window``.
- *Processed frames* (the system verdict): a detector that needs L seconds per frame takes the first frame,
  then the first frame that arrives once it is free again (t >= the last taken + L).
- *Outcome*: the ego holds the closing speed dv it had at the lane change (the simulated ego's ACC sees the
  ground truth and brakes before any detector could tell it to, so its own speed is not the detector's
  outcome). At the decision time (confirmation + latency + reaction) the gap is d0 - dv (t - t0); the
  deceleration needed to stop ``stop_gap`` metres short is a_req = dv^2 / (2 (gap - stop_gap)), and the
  margin is the gap left over at a given deceleration: gap - stop_gap - dv^2 / (2 a).

Pure functions; constants and their sources: ``simulator.scenario`` and docs/simulator.md.
"""
from __future__ import annotations

import math

import numpy as np

from harness.core.braking import A_PASS_MPS2, MARGIN_M

CONFIRM_K = 3  # hits ...
CONFIRM_WINDOW_S = 0.5  # ... within this many seconds confirm the obstacle
_EPS = 1e-6  # s, frame times are rounded to the millisecond


def frame_period(times) -> float:
    """The median step (s) between consecutive frame times; nan with fewer than two frames."""
    t = np.asarray(times, dtype=np.float64)
    return float(np.median(np.diff(t))) if t.size > 1 else float("nan")


def confirm_window(window_s: float, k: int, period_s: float) -> float:
    """Seconds of the confirmation window: ``window_s``, or k frame periods where that is longer."""
    return max(float(window_s), k * period_s) if np.isfinite(period_s) else float(window_s)


def confirm_index(times, hits, k: int = CONFIRM_K, window_s: float = CONFIRM_WINDOW_S) -> int | None:
    """Index of the first hit frame i with at least k hits among the frames in (t_i - window_s, t_i];
    None when no frame is. ``times`` ascending, seconds."""
    if k < 1 or window_s <= 0:
        raise ValueError(f"confirmation needs k >= 1 and a window > 0 s, got k={k}, window {window_s} s")
    t = np.asarray(times, dtype=np.float64)
    h = np.asarray(hits, dtype=bool)
    if t.size == 0:
        return None
    csum = np.r_[0, np.cumsum(h)]  # csum[i] = hits in frames 0..i-1
    first = np.searchsorted(t, t - window_s + _EPS, side="left")  # first frame inside each window
    count = csum[1:] - csum[first]
    idx = np.flatnonzero(h & (count >= k))
    return int(idx[0]) if idx.size else None


def processed_frames(times, latency_s: float) -> np.ndarray:
    """(F,) bool: the frames a detector taking ``latency_s`` per frame processes (the first, then the first to
    arrive once it is free). Every frame when the latency is 0."""
    if latency_s < 0:
        raise ValueError(f"latency must be >= 0 s, got {latency_s}")
    t = np.asarray(times, dtype=np.float64)
    keep = np.zeros(t.size, dtype=bool)
    free = -math.inf
    for i, ti in enumerate(t):
        if ti >= free - _EPS:
            keep[i], free = True, ti + latency_s
    return keep


def a_required(gap_m: float, closing_mps: float, stop_gap_m: float = MARGIN_M) -> float:
    """m/s^2 needed to match the obstacle's speed ``stop_gap_m`` short of it from ``gap_m``; 0 when not closing
    in, inf when the gap is already that short."""
    if closing_mps <= 0:
        return 0.0
    room = gap_m - stop_gap_m
    return closing_mps**2 / (2.0 * room) if room > 0 else math.inf


def margin_m(gap_m: float, closing_mps: float, decel: float = A_PASS_MPS2, stop_gap_m: float = MARGIN_M) -> float:
    """Metres to spare when braking at ``decel`` from ``gap_m`` (negative: it is not enough)."""
    dv = max(float(closing_mps), 0.0)
    return gap_m - stop_gap_m - dv * dv / (2.0 * decel)


def outcome(d0: float, closing_mps: float, decision_after_s: float) -> dict:
    """``{gap_m, a_req_mps2, margin_m}`` at a decision ``decision_after_s`` seconds after the situation (d0, dv)."""
    gap = d0 - max(closing_mps, 0.0) * decision_after_s
    return {"gap_m": gap, "a_req_mps2": a_required(gap, closing_mps), "margin_m": margin_m(gap, closing_mps)}


def passes(a_req: float, limit: float = A_PASS_MPS2) -> bool:
    return bool(a_req <= limit)


def unpreventable_reason(kinematics_ok: bool, range_only_ok: bool, occlusion_only_ok: bool) -> str:
    """Why the reference (confirming as soon as the obstacle is perceivable) could not pass: "kinematics" when not
    even a perception that sees it in every frame after the lane change passes; else what held the reference back:
    "occlusion" when it passes counting only the range, "range" when it passes counting only the occlusion, else
    "occlusion and range"."""
    if not kinematics_ok:
        return "kinematics"
    if range_only_ok != occlusion_only_ok:
        return "occlusion" if range_only_ok else "range"
    return "occlusion and range"
