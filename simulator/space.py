"""The cut-out scenario as a space: instances from a seeded space-filling design, and the sweep's weather.

An instance fixes ego speed, slow-car speed, cut-out gap, lane-change duration, the slow car's lateral
offset in its lane, the slow car's body and paint (with the paint's measured 905 nm reflectance, which
the LiDAR sees through the vehicle's reflectance override) and the fast car's body. The design is a
Latin hypercube (scipy.stats.qmc) seeded from the data set's seed: the same seed and instance count
give the same instances. In the SOTIF instance set, instance 0 is the source study's scenario (the
SotifConfig defaults) and instances 1..N-1 are the design's points; every weather preset runs the same
instances (a paired design). The sweep set draws N design points, each with one weather axis
(round-robin rain / fog / water) and its value from one more design column. Values and their sources:
docs/simulator.md.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
from scipy.stats import qmc

from simulator.scenario import SotifConfig
from simulator.vehicles import BODY_TYPES
from simulator.weather import MOR_AT_FULL_FOG_M, WEATHER_PRESETS, WeatherPreset, precipitation_for_rate

# name: (paint whose albedo the camera renders, reflectance at 905 nm); sources in docs/simulator.md
SLOW_PAINTS: dict[str, tuple[str, float]] = {
    "silver": ("silver", 0.57),  # aluminium-flake silver shell (Levinson et al. 2011)
    "white": ("white", 0.60),  # white shell (Levinson et al. 2011)
    "black": ("black", 0.05),  # carbon-black shell (Levinson et al. 2011)
    "nir_black": ("black", 0.60),  # NIR-reflective dark bilayer, >= 60 % at 905 nm (Lim et al. 2022)
}
SLOW_BODIES = ("sedan", "hatchback", "suv", "van", "truck")
FAST_BODIES = ("sedan", "hatchback", "suv", "van")
FAST_PAINT = "red"
SWEEP_AXES = ("rain", "fog", "water")
SWEEP_WEATHER = "Sweep"  # the weather name of sweep frames
SWEEP_BASE = "ClearNoon"  # light and sky of the sweep set
DESIGN_TAG = 45  # the design's random stream: default_rng([seed, DESIGN_TAG, sweep])


@dataclass(frozen=True)
class ScenarioSpace:
    """Ranges (min, max) of the scenario space and the recording of an instance set; part of the config."""

    instances: int
    ego_speed_kmh: tuple[float, float] = (80.0, 130.0)
    slow_speed_kmh: tuple[float, float] = (30.0, 80.0)
    cutout_gap_m: tuple[float, float] = (5.0, 20.0)
    lane_change_s: tuple[float, float] = (2.5, 5.0)
    lateral_offset_m: tuple[float, float] = (-0.5, 0.5)
    rain_mmh: tuple[float, float] = (0.0, 100.0)  # sweep: rain rate
    fog_mor_m: tuple[float, float] = (50.0, 2000.0)  # sweep: meteorological optical range, log-uniform
    road_water: tuple[float, float] = (0.0, 1.0)  # sweep: share of the road under water, no rain
    val_share: float = 0.1  # instances per weather in the val split (never instance 0)
    lead_in_frames: int = 2  # 2 Hz frames before the lane change
    window_slack_s: float = 0.3  # recorded (at 10 Hz) past the latest moment a confirmation can still pass
    window_max_s: float = 7.5  # nothing recorded later than this after the cut-out (the study's window: 7.2 s)
    sweep: bool = False
    probes: tuple = ()  # a bounds set's probes (simulator.bounds.Probe), one instance each; () otherwise


@dataclass(frozen=True)
class Instance:
    """One cut-out: the parameters an instance fixes (the sc_* columns of meta/frames.csv)."""

    ego_speed_kmh: float
    slow_speed_kmh: float
    cutout_gap_m: float
    lane_change_s: float
    lateral_offset_m: float
    slow_body: str
    slow_paint: str
    slow_reflectance: float
    fast_body: str

    def sotif_config(self, base: SotifConfig = SotifConfig()) -> SotifConfig:
        paint = SLOW_PAINTS[self.slow_paint][0]
        return replace(base, ego_speed=self.ego_speed_kmh / 3.6, slow_speed=self.slow_speed_kmh / 3.6,
                       trigger_gap=self.cutout_gap_m, lane_change_duration=self.lane_change_s,
                       slow_body=(self.slow_body, BODY_TYPES[self.slow_body].dims, paint),
                       fast_body=(self.fast_body, BODY_TYPES[self.fast_body].dims, FAST_PAINT))

    def columns(self) -> dict:
        return {f"sc_{k}": (round(v, 4) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


STUDY = Instance(90.0, 60.0, 10.0, 3.5, 0.0, "sedan", "silver", SLOW_PAINTS["silver"][1], "hatchback")
PARAMETERS = tuple(Instance.__dataclass_fields__)
CONTINUOUS = ("ego_speed_kmh", "slow_speed_kmh", "cutout_gap_m", "lane_change_s", "lateral_offset_m")


def check_space(space: ScenarioSpace) -> None:
    """ValueError naming the bad field: an instance count < 1, a range with min > max or outside its domain."""
    if not isinstance(space.instances, (int, np.integer)) or isinstance(space.instances, bool) or space.instances < 1:
        raise ValueError(f"instances must be an integer >= 1, got {space.instances!r}")
    if space.probes and (space.instances != len(space.probes) or not space.sweep):
        raise ValueError(f"a bounds set is a sweep of one instance per probe: {space.instances} instances, "
                         f"{len(space.probes)} probes")
    for name in CONTINUOUS + ("rain_mmh", "fog_mor_m", "road_water"):
        lo, hi = getattr(space, name)
        if not lo <= hi:
            raise ValueError(f"scenario range {name}: min {lo} > max {hi}")
    if space.slow_speed_kmh[1] > space.ego_speed_kmh[0]:
        raise ValueError(f"scenario ranges: slow_speed_kmh max {space.slow_speed_kmh[1]} exceeds ego_speed_kmh "
                         f"min {space.ego_speed_kmh[0]} (the ego must close in on the slow car)")
    if space.fog_mor_m[0] <= 0 or space.rain_mmh[0] < 0 or not 0 <= space.road_water[0] <= space.road_water[1] <= 1:
        raise ValueError("scenario ranges: fog_mor_m must be > 0, rain_mmh >= 0, road_water within [0, 1]")


def _pick(u: float, names: tuple) -> str:
    return names[min(int(u * len(names)), len(names) - 1)]


def _scale(u: float, lo_hi: tuple[float, float]) -> float:
    return float(lo_hi[0] + u * (lo_hi[1] - lo_hi[0]))


def design(space: ScenarioSpace, seed: int) -> np.ndarray:
    """(n, 8) or, for the sweep, (n, 9) Latin hypercube points in [0, 1): the SOTIF set's instances 1..N-1
    (instance 0 is the study), the sweep's instances 0..N-1 (its last column is the axis value)."""
    n = space.instances if space.sweep else space.instances - 1
    d = len(PARAMETERS) - 1 + (1 if space.sweep else 0)  # the reflectance follows the paint
    if n == 0:
        return np.zeros((0, d))
    return qmc.LatinHypercube(d, rng=np.random.default_rng([seed, DESIGN_TAG, int(space.sweep)])).random(n)


def instance_from(u: np.ndarray, space: ScenarioSpace) -> Instance:
    """The instance of one design point u (8 or more numbers in [0, 1))."""
    paint = _pick(u[5], tuple(SLOW_PAINTS))
    return Instance(*(_scale(u[i], getattr(space, name)) for i, name in enumerate(CONTINUOUS)),
                    _pick(u[6], SLOW_BODIES), paint, SLOW_PAINTS[paint][1], _pick(u[7], FAST_BODIES))


@lru_cache(maxsize=8)
def instances(space: ScenarioSpace, seed: int) -> tuple[Instance, ...]:
    """The set's instances in order (SOTIF: instance 0 is the study's scenario; a bounds set: its probes')."""
    if space.probes:
        return tuple(p.instance() for p in space.probes)
    drawn = tuple(instance_from(u, space) for u in design(space, seed))
    return drawn if space.sweep else (STUDY,) + drawn


def val_instances(n: int, share: float) -> set[int]:
    """Instances of the val split: round(share * n) (at least 1 when n >= 2 and share > 0), spread over 1..n-1."""
    if n < 2 or share <= 0:
        return set()
    k = max(1, int(round(share * n)))
    return set(np.unique(np.linspace(1, n - 1, k).round().astype(int)).tolist())


@dataclass(frozen=True)
class SweepPoint:
    axis: str  # "rain", "fog" or "water"
    value: float  # mm/h, m (MOR) or share of the road under water


@lru_cache(maxsize=8)
def sweep_points(space: ScenarioSpace, seed: int) -> tuple[SweepPoint, ...]:
    """Instance i's weather: axis SWEEP_AXES[i % 3], value from the design's last column (fog log-uniform); a
    bounds set's: its probe's axis and value."""
    if space.probes:
        return tuple(p.point() for p in space.probes)
    out = []
    for i, u in enumerate(design(space, seed)[:, -1]):
        axis = SWEEP_AXES[i % len(SWEEP_AXES)]
        if axis == "fog":
            lo, hi = space.fog_mor_m
            value = float(lo * (hi / lo) ** u)
        else:
            value = _scale(u, space.rain_mmh if axis == "rain" else space.road_water)
        out.append(SweepPoint(axis, value))
    return tuple(out)


def sweep_weather(point: SweepPoint) -> WeatherPreset:
    """The WeatherPreset of a sweep point on SWEEP_BASE's light: rain at its physical rate (with the road water
    the precipitation slider of that rate implies), fog seen by LiDAR and camera from the sensor on, or road
    water alone (CARLA's puddle deposits)."""
    base = WEATHER_PRESETS[SWEEP_BASE]
    if point.axis == "rain":
        return replace(base, precipitation=precipitation_for_rate(point.value), rain_rate_override_mmh=point.value)
    if point.axis == "fog":
        return replace(base, lidar_fog_mor_m=point.value, fog_density=MOR_AT_FULL_FOG_M * 100.0 / point.value,
                       fog_distance=0.0)
    if point.axis == "water":
        return replace(base, precipitation_deposits=100.0 * point.value)
    return base

