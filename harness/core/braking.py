"""The braking rule that the simulator's scenario and the harness's SOTIF verdict share.

The ego needs ``stopping_distance(dv)`` metres to match the speed of a car it closes in on at
``dv`` m/s: a reaction time at ``dv``, then a constant deceleration, and a margin left over.
"""
from __future__ import annotations

EGO_DIMS = (4.7, 1.85, 1.5)  # m, the ego's length, width and height
T_REACT_S = 1.0  # s, driver/system reaction time before braking starts
DECEL_MPS2 = 4.0  # m/s^2, comfortable-to-firm braking deceleration
MARGIN_M = 2.0  # m, gap left after braking


def stopping_distance(closing_speed_mps: float, t_react: float = T_REACT_S, decel: float = DECEL_MPS2,
                      margin: float = MARGIN_M) -> float:
    """Distance (m) the ego needs to match the slow car's speed; a non-closing ego needs only the margin."""
    dv = max(float(closing_speed_mps), 0.0)
    return dv * t_react + dv * dv / (2.0 * decel) + margin
