"""The braking rule that the simulator's scenario and the harness's SOTIF verdict share.

The ego needs ``stopping_distance(dv)`` metres to match the speed of a car it closes in on at
``dv`` m/s: a reaction time at ``dv``, then a constant deceleration, and a margin left over.
"""
from __future__ import annotations

EGO_DIMS = (4.7, 1.85, 1.5)  # m, the ego's length, width and height
T_REACT_S = 1.0  # s, a human driver's reaction time before braking starts (the verdict's human option)
DECEL_MPS2 = 4.0  # m/s^2, comfortable-to-firm braking deceleration (shown beside the pass criterion)
MARGIN_M = 2.0  # m, gap left after braking
# The SOTIF verdict's pass criterion (harness.verdict; sources in docs/simulator.md): an automated system starts
# to brake 0.35 s after it has confirmed the obstacle and brakes at up to 6 m/s^2 (UN R157, para. 5.2.5.2).
T_REACT_SYSTEM_S = 0.35  # s
A_PASS_MPS2 = 6.0  # m/s^2


def stopping_distance(closing_speed_mps: float, t_react: float = T_REACT_S, decel: float = DECEL_MPS2,
                      margin: float = MARGIN_M) -> float:
    """Distance (m) the ego needs to match the slow car's speed; a non-closing ego needs only the margin."""
    dv = max(float(closing_speed_mps), 0.0)
    return dv * t_react + dv * dv / (2.0 * decel) + margin
