"""The 21 CARLA weather presets and the quantities the sensor models derive from them.

Values are CARLA 0.9.15's `WeatherParameters` presets (LibCarla/source/carla/rpc/
WeatherParameters.cpp), same names and numbers, including CARLA's own spelling
(`MidRainyNoon`, `MidRainSunset`, `MidRainyNight`).

Mappings chosen here (CARLA's parameters are rendering sliders, not physical units):
- rain rate: `rain_rate_mmh = 50 * (precipitation / 100) ** 2`, so SoftRain (30) = 4.5 mm/h
  (moderate), MidRain (60) = 18 mm/h (heavy), HardRain (100) = 50 mm/h (violent).
- precipitation class: "rain" when precipitation > 0, "wet" when only wetness or puddle
  deposits are set, else "dry".
- road water cover in [0, 1]: max(precipitation_deposits, wetness, precipitation) / 100.
- fog, camera: CARLA's fog_density (0..100) maps linearly to an extinction coefficient of the
  rendered haze with density 100 = meteorological optical range 1000 m (mist).
- fog, LiDAR: none in the 21 presets. CARLA's fog_density is a rendering device (its night presets
  carry 60-100 to darken the image, and CARLA's weather changes only the camera), so a clear night
  is a clear atmosphere for a 905 nm LiDAR. A preset is a fog preset for the LiDAR only when it sets
  `lidar_fog_mor_m` (the fog's meteorological optical range, m): then the LiDAR sees Beer-Lambert
  extinction alpha = -ln(0.05) / MOR and Hahner et al.'s soft-target back-scatter, beyond
  fog_distance metres from the sensor.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

MOR_AT_FULL_FOG_M = 1000.0  # meteorological optical range at fog_density = 100
MAX_RAIN_RATE_MMH = 50.0  # rain rate at precipitation = 100


@dataclass(frozen=True)
class WeatherPreset:
    """CARLA WeatherParameters (angles in degrees, sliders 0..100, distances in metres)."""

    cloudiness: float
    precipitation: float
    precipitation_deposits: float
    wind_intensity: float
    sun_azimuth_angle: float
    sun_altitude_angle: float
    fog_density: float
    fog_distance: float
    fog_falloff: float
    wetness: float
    scattering_intensity: float = 1.0
    mie_scattering_scale: float = 0.03
    rayleigh_scattering_scale: float = 0.0331
    dust_storm: float = 0.0
    lidar_fog_mor_m: float = 0.0  # physical fog the LiDAR sees (MOR, m); 0 = none (not a CARLA parameter)
    rain_rate_override_mmh: float | None = None  # physical rain rate (mm/h) instead of the slider's; None = slider

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def _wp(*values: float) -> WeatherPreset:
    return WeatherPreset(*values)


#                         cloud  precip  deposits  wind  azimuth  altitude  fog  fog_dist  falloff  wetness
WEATHER_PRESETS: dict[str, WeatherPreset] = {
    "ClearNoon": _wp(5.0, 0.0, 0.0, 10.0, -1.0, 45.0, 2.0, 0.75, 0.1, 0.0),
    "CloudyNoon": _wp(60.0, 0.0, 0.0, 10.0, -1.0, 45.0, 3.0, 0.75, 0.1, 0.0),
    "WetNoon": _wp(5.0, 0.0, 50.0, 10.0, -1.0, 45.0, 3.0, 0.75, 0.1, 0.0),
    "WetCloudyNoon": _wp(60.0, 0.0, 50.0, 10.0, -1.0, 45.0, 3.0, 0.75, 0.1, 0.0),
    "MidRainyNoon": _wp(60.0, 60.0, 60.0, 60.0, -1.0, 45.0, 3.0, 0.75, 0.1, 0.0),
    "HardRainNoon": _wp(100.0, 100.0, 90.0, 100.0, -1.0, 45.0, 7.0, 0.75, 0.1, 0.0),
    "SoftRainNoon": _wp(20.0, 30.0, 50.0, 30.0, -1.0, 45.0, 3.0, 0.75, 0.1, 0.0),
    "ClearSunset": _wp(5.0, 0.0, 0.0, 10.0, -1.0, 15.0, 2.0, 0.75, 0.1, 0.0),
    "CloudySunset": _wp(60.0, 0.0, 0.0, 10.0, -1.0, 15.0, 3.0, 0.75, 0.1, 0.0),
    "WetSunset": _wp(5.0, 0.0, 50.0, 10.0, -1.0, 15.0, 2.0, 0.75, 0.1, 0.0),
    "WetCloudySunset": _wp(60.0, 0.0, 50.0, 10.0, -1.0, 15.0, 2.0, 0.75, 0.1, 0.0),
    "MidRainSunset": _wp(60.0, 60.0, 60.0, 60.0, -1.0, 15.0, 3.0, 0.75, 0.1, 0.0),
    "HardRainSunset": _wp(100.0, 100.0, 90.0, 100.0, -1.0, 15.0, 7.0, 0.75, 0.1, 0.0),
    "SoftRainSunset": _wp(20.0, 30.0, 50.0, 30.0, -1.0, 15.0, 2.0, 0.75, 0.1, 0.0),
    "ClearNight": _wp(5.0, 0.0, 0.0, 10.0, -1.0, -90.0, 60.0, 75.0, 1.0, 0.0),
    "CloudyNight": _wp(60.0, 0.0, 0.0, 10.0, -1.0, -90.0, 60.0, 0.75, 0.1, 0.0),
    "WetNight": _wp(5.0, 0.0, 50.0, 10.0, -1.0, -90.0, 60.0, 75.0, 1.0, 60.0),
    "WetCloudyNight": _wp(60.0, 0.0, 50.0, 10.0, -1.0, -90.0, 60.0, 0.75, 0.1, 60.0),
    "SoftRainNight": _wp(60.0, 30.0, 50.0, 30.0, -1.0, -90.0, 60.0, 0.75, 0.1, 60.0),
    "MidRainyNight": _wp(80.0, 60.0, 60.0, 60.0, -1.0, -90.0, 60.0, 0.75, 0.1, 80.0),
    "HardRainNight": _wp(100.0, 100.0, 90.0, 100.0, -1.0, -90.0, 100.0, 0.75, 0.1, 100.0),
}

DRY_PRESETS: tuple[str, ...] = tuple(
    name for name, p in WEATHER_PRESETS.items()
    if p.precipitation == 0 and p.precipitation_deposits == 0 and p.wetness == 0
)


def get_preset(name: str) -> WeatherPreset:
    """Preset by CARLA name; ValueError naming the valid names otherwise."""
    if name not in WEATHER_PRESETS:
        raise ValueError(f"unknown weather preset {name!r}; valid: {', '.join(WEATHER_PRESETS)}")
    return WEATHER_PRESETS[name]


def rain_rate_mmh(p: WeatherPreset) -> float:
    """Rain rate in mm/h: the weather's physical override, else from CARLA's precipitation slider (see module
    docstring; the slider reaches MAX_RAIN_RATE_MMH, the override any rate)."""
    if p.rain_rate_override_mmh is not None:
        return float(p.rain_rate_override_mmh)
    return MAX_RAIN_RATE_MMH * (p.precipitation / 100.0) ** 2


def precipitation_for_rate(rate_mmh: float) -> float:
    """The precipitation slider (0..100) whose rain rate is ``rate_mmh``, 100 beyond MAX_RAIN_RATE_MMH."""
    return min(100.0, 100.0 * math.sqrt(max(rate_mmh, 0.0) / MAX_RAIN_RATE_MMH))


def time_of_day(p: WeatherPreset) -> str:
    """"Noon", "Sunset" or "Night" from the sun altitude in degrees."""
    if p.sun_altitude_angle < 0:
        return "Night"
    return "Sunset" if p.sun_altitude_angle < 30 else "Noon"


def precipitation_class(p: WeatherPreset) -> str:
    """"rain" if it rains, "wet" if only the road is wet, else "dry"."""
    if p.precipitation > 0:
        return "rain"
    return "wet" if max(p.wetness, p.precipitation_deposits) > 0 else "dry"


def road_water_cover(p: WeatherPreset) -> float:
    """Share of the road surface under a water film, in [0, 1]."""
    return min(1.0, max(p.precipitation_deposits, p.wetness, p.precipitation) / 100.0)


def fog_extinction(p: WeatherPreset) -> float:
    """Extinction coefficient of the camera's rendered haze in 1/m (Koschmieder: alpha = -ln(0.05) / MOR)."""
    if p.fog_density <= 0:
        return 0.0
    mor = MOR_AT_FULL_FOG_M * 100.0 / p.fog_density
    return -math.log(0.05) / mor


def lidar_fog_extinction(p: WeatherPreset) -> float:
    """Extinction coefficient (1/m) of the fog the LiDAR sees: -ln(0.05) / lidar_fog_mor_m, 0 without fog."""
    return -math.log(0.05) / p.lidar_fog_mor_m if p.lidar_fog_mor_m > 0 else 0.0
