"""Controlled sweeps: reference scenarios held fixed and one axis varied, the probes of a boundary search.

A *reference scenario* fixes everything an instance fixes (``simulator.space.Instance``): one of two kinematic
settings (the study's ego 90 km/h behind a fast car, slow car 60 km/h, cut-out 10 m behind it; and ego 120 km/h
on the same slow car), the slow car's body (sedan or SUV) and paint (silver 0.57 or black 0.05 at 905 nm, the
table of ``simulator.space.SLOW_PAINTS``), with the study's 3.5 s lane change, no lateral offset and a red
hatchback as the fast car. Its background traffic is drawn once per reference scenario and data-set seed.

A *probe* is (reference scenario, axis, value, noise seed): the reference scenario under clear noon light with
one axis moved: rain rate (mm/h), fog visibility (MOR, m), road water (share of the road under water, no
rain), or the slow car's 905 nm reflectance (its paint's albedo stays as the camera's). Every other factor
stays at the reference: clear air, a dry road and the paint's reflectance. The noise seed keys the sensors'
random streams with the reference scenario and the step only, so that probes of one scenario and seed differ by
their axis value alone (common random numbers), and another seed redraws the sensor noise, the rain and fog
returns and the spray. ``generate(preset="bounds", probes=...)`` writes a set of probes (all test frames);
meta/frames.csv carries ``reference_scenario``, ``sweep_axis``, ``axis_value`` and ``noise_seed``.
Values and their sources: docs/simulator.md.
"""
from __future__ import annotations

from dataclasses import dataclass

from simulator.space import SLOW_PAINTS, SWEEP_AXES, Instance, ScenarioSpace, SweepPoint

KINEMATICS = {"90-60": (90.0, 60.0), "120-60": (120.0, 60.0)}  # ego, slow car km/h
BODIES = ("sedan", "suv")
PAINTS = ("silver", "black")
CUTOUT_GAP_M, LANE_CHANGE_S, FAST_BODY = 10.0, 3.5, "hatchback"  # the study's
AXES = SWEEP_AXES + ("reflectance",)
_SPACE = ScenarioSpace(1)
# axis: (low end, high end, unit); rain, fog and water as the drawn sweep's ranges
AXIS_RANGES = {"rain": (*_SPACE.rain_mmh, "mm/h"), "fog": (*_SPACE.fog_mor_m, "m"),
               "water": (*_SPACE.road_water, "share"), "reflectance": (0.02, 0.8, "reflectance")}
PROBE_COLUMNS = ("reference_scenario", "axis_value", "noise_seed")
STREAM_TAG = 25  # background traffic: default_rng([seed, STREAM_TAG, reference scenario's index])


@dataclass(frozen=True)
class ReferenceScenario:
    name: str
    index: int  # keys the scenario's random streams
    ego_speed_kmh: float
    slow_speed_kmh: float
    slow_body: str
    slow_paint: str

    def instance(self, reflectance: float | None = None) -> Instance:
        """The scenario as an instance, its slow car at ``reflectance`` (None: its paint's)."""
        rho = SLOW_PAINTS[self.slow_paint][1] if reflectance is None else float(reflectance)
        return Instance(self.ego_speed_kmh, self.slow_speed_kmh, CUTOUT_GAP_M, LANE_CHANGE_S, 0.0, self.slow_body,
                        self.slow_paint, rho, FAST_BODY)


def _references() -> dict[str, ReferenceScenario]:
    out = {}
    for kin, (ego, slow) in KINEMATICS.items():
        for body in BODIES:
            for paint in PAINTS:
                name = f"{kin}_{body}_{paint}"
                out[name] = ReferenceScenario(name, len(out), ego, slow, body, paint)
    return out


REFERENCES = _references()
STUDY_REFERENCE = "90-60_sedan_silver"  # the study's scenario (simulator.space.STUDY but for the fast car: the same)


def reference_value(scenario: str, axis: str) -> float:
    """The axis's value in the reference scenario itself: no rain, no fog (the far end), a dry road, its paint."""
    if axis == "reflectance":
        return SLOW_PAINTS[REFERENCES[scenario].slow_paint][1]
    return AXIS_RANGES[axis][1] if axis == "fog" else AXIS_RANGES[axis][0]


@dataclass(frozen=True)
class Probe:
    """One instance of a controlled sweep (module docstring)."""

    scenario: str
    axis: str
    value: float
    noise_seed: int = 0

    def instance(self) -> Instance:
        return REFERENCES[self.scenario].instance(self.value if self.axis == "reflectance" else None)

    def point(self) -> SweepPoint:
        """The probe's weather (``simulator.space.sweep_weather``): clear for the reflectance axis."""
        return SweepPoint(self.axis, float(self.value))

    def held_key(self) -> list[int]:
        """What keys the random streams held fixed across the probe's sweep: the reference scenario."""
        return [REFERENCES[self.scenario].index]

    def columns(self) -> dict:
        return {"reference_scenario": self.scenario, "axis_value": round(float(self.value), 6),
                "noise_seed": int(self.noise_seed)}


def check_probes(probes) -> tuple[Probe, ...]:
    """The probes as a tuple; ValueError naming the first unknown scenario or axis, a value outside its axis's
    range, a negative or non-integer noise seed, or no probe at all."""
    probes = tuple(probes)
    if not probes:
        raise ValueError("a bounds set needs at least one probe")
    for p in probes:
        if not isinstance(p, Probe):
            raise ValueError(f"a probe must be a simulator.bounds.Probe, got {p!r}")
        if p.scenario not in REFERENCES:
            raise ValueError(f"unknown reference scenario {p.scenario!r}; known: {', '.join(REFERENCES)}")
        if p.axis not in AXES:
            raise ValueError(f"unknown axis {p.axis!r}; known: {', '.join(AXES)}")
        lo, hi, unit = AXIS_RANGES[p.axis]
        if not lo <= p.value <= hi:
            raise ValueError(f"axis {p.axis}: value {p.value} outside {lo}-{hi} {unit}")
        if isinstance(p.noise_seed, bool) or not isinstance(p.noise_seed, int) or p.noise_seed < 0:
            raise ValueError(f"noise seed must be an integer >= 0, got {p.noise_seed!r}")
    return probes
