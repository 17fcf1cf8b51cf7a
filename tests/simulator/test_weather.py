import math

import pytest

from simulator.weather import (DRY_PRESETS, WEATHER_PRESETS, fog_extinction, get_preset, precipitation_class,
                               rain_rate_mmh, road_water_cover, time_of_day)

# CARLA 0.9.15 WeatherParameters.cpp (cloudiness, precipitation, deposits, sun altitude, fog density, wetness)
CARLA_TABLE = """
ClearNoon 5 0 0 45 2 0
CloudyNoon 60 0 0 45 3 0
WetNoon 5 0 50 45 3 0
WetCloudyNoon 60 0 50 45 3 0
MidRainyNoon 60 60 60 45 3 0
HardRainNoon 100 100 90 45 7 0
SoftRainNoon 20 30 50 45 3 0
ClearSunset 5 0 0 15 2 0
CloudySunset 60 0 0 15 3 0
WetSunset 5 0 50 15 2 0
WetCloudySunset 60 0 50 15 2 0
MidRainSunset 60 60 60 15 3 0
HardRainSunset 100 100 90 15 7 0
SoftRainSunset 20 30 50 15 2 0
ClearNight 5 0 0 -90 60 0
CloudyNight 60 0 0 -90 60 0
WetNight 5 0 50 -90 60 60
WetCloudyNight 60 0 50 -90 60 60
SoftRainNight 60 30 50 -90 60 60
MidRainyNight 80 60 60 -90 60 80
HardRainNight 100 100 90 -90 100 100
"""


def test_presets_match_carla_table():
    rows = [line.split() for line in CARLA_TABLE.strip().splitlines()]
    assert list(WEATHER_PRESETS) == [r[0] for r in rows]
    for name, *vals in rows:
        p = WEATHER_PRESETS[name]
        got = (p.cloudiness, p.precipitation, p.precipitation_deposits, p.sun_altitude_angle, p.fog_density, p.wetness)
        assert got == tuple(float(v) for v in vals), name


def test_derived_quantities():
    assert DRY_PRESETS == ("ClearNoon", "CloudyNoon", "ClearSunset", "CloudySunset", "ClearNight", "CloudyNight")
    rates = [rain_rate_mmh(WEATHER_PRESETS[n]) for n in ("ClearNoon", "SoftRainNoon", "MidRainyNoon", "HardRainNoon")]
    assert rates == sorted(rates) and rates[0] == 0 and rates[-1] == pytest.approx(50.0)
    assert [time_of_day(WEATHER_PRESETS[n]) for n in ("WetNoon", "MidRainSunset", "HardRainNight")] == \
        ["Noon", "Sunset", "Night"]
    assert [precipitation_class(WEATHER_PRESETS[n]) for n in ("CloudyNoon", "WetNight", "SoftRainSunset")] == \
        ["dry", "wet", "rain"]
    assert road_water_cover(WEATHER_PRESETS["ClearNoon"]) == 0 and road_water_cover(WEATHER_PRESETS["WetNoon"]) == 0.5
    # Koschmieder: transmission over the MOR is 5 %
    p = WEATHER_PRESETS["HardRainNight"]
    assert math.exp(-fog_extinction(p) * 1000.0) == pytest.approx(0.05)


def test_unknown_preset_names_valid_ones():
    with pytest.raises(ValueError, match="ClearNoon"):
        get_preset("Sunny")


def test_no_carla_preset_is_a_fog_preset_for_the_lidar():
    """CARLA's fog_density (60-100 at night) is a rendering device: the LiDAR sees fog only in a fog preset."""
    from dataclasses import replace

    from simulator.weather import lidar_fog_extinction

    assert all(lidar_fog_extinction(p) == 0.0 for p in WEATHER_PRESETS.values())
    assert WEATHER_PRESETS["ClearNight"].fog_density == 60.0 and fog_extinction(WEATHER_PRESETS["ClearNight"]) > 0
    fog = replace(WEATHER_PRESETS["ClearNoon"], lidar_fog_mor_m=80.0)
    assert math.exp(-lidar_fog_extinction(fog) * 80.0) == pytest.approx(0.05)  # Koschmieder
