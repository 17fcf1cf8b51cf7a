"""Ray-casting simulator of the SOTIF highway use case, writing KITTI data sets.

`generate(out, preset="sotif"|"train", ...)` writes the data set (see simulator.dataset);
`WEATHER_PRESETS` holds CARLA's 21 weather presets (see simulator.weather).
"""
from simulator.dataset import generate
from simulator.weather import WEATHER_PRESETS

__all__ = ["WEATHER_PRESETS", "generate"]
