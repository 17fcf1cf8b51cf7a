"""One frame: scene state -> LiDAR scan, camera image, labels, calib, meta row (files on disk).

meta row: slow_car_label_index / fast_car_label_index give the row of that vehicle in the
frame's label_2 file (-1 when it is not in the camera image; the row is a DontCare row when
the vehicle is hidden or beyond the labelling distance). Training scenes have neither.

Worlds, their Embree scenes and the SOTIF trajectories are cached per process. Random
streams are seeded per frame: the LiDAR's from (seed, scenario, scenario step) for SOTIF so
that a weather-blind sensor gives the same scan in every weather (instance mode: from (seed, scenario,
instance, step); a bounds set's probe, LiDAR and camera: from (seed, scenario, reference scenario, noise
seed, step)), the rest from the frame index.
"""
from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from harness.core import kitti
from harness.core.files import atomic_write_bytes
from simulator import fidelity
from simulator.bounds import PROBE_COLUMNS, STREAM_TAG
from simulator.camera import render
from simulator.labels import frame_labels, lidar_boxes
from simulator.lidar import Pose, scan
from simulator.raycast import RayScene
from simulator.scenario import FrameState, run_steps, sotif_run, training_scene
from simulator.space import SWEEP_WEATHER, Instance, instances, sweep_points, sweep_weather
from simulator.weather import (WEATHER_PRESETS, WeatherPreset, precipitation_class, rain_rate_mmh, road_water_cover,
                               time_of_day)
from simulator.world import build_world

SCENARIO_TAG = {"sotif": 1, "train": 2, "sweep": 3, "bounds": 4}
WORLD_TAG = {"sotif": 11, "train": 12, "sweep": 11, "bounds": 11}  # the sweeps drive on the SOTIF set's highway
TRAIN_FRAMES_PER_WORLD = 100
MIN_RUN_FRAMES = 27  # the scenario is always simulated to its end (lane change included)
ROW_COLUMNS = ("frame_id", "split", "scenario", "weather", "time_of_day", "precipitation_class", "cloudiness",
               "precipitation", "precipitation_deposits", "wetness", "fog_density", "fog_distance",
               "wind_intensity", "sun_altitude_angle", "rain_rate_mmh", "scenario_time_s", "ego_speed_mps",
               "slow_car_speed_mps", "lane_change_time_s", "cutout_time_s", "slow_car_label_index", "fast_car_label_index",
               "slow_car_distance_m", "n_points", "n_vehicles", "lidar_model") + fidelity.COLUMNS
INSTANCE_COLUMNS = ("instance", "instance_key", "sweep_axis", "fog_mor_m", "road_water", "in_window",
                    "sc_ego_speed_kmh", "sc_slow_speed_kmh", "sc_cutout_gap_m", "sc_lane_change_s",
                    "sc_lateral_offset_m", "sc_slow_body", "sc_slow_paint", "sc_slow_reflectance", "sc_fast_body")
_SCENES: dict = {}
_RUNS: dict = {}


@dataclass(frozen=True)
class FrameJob:
    index: int  # position in the data set
    frame_id: str  # 6 digits
    weather: str
    step: int  # recorded step of the SOTIF run (training: = index)
    split: str
    run_length: int  # recorded frames of the longest SOTIF run (instance mode: steps of the instance's run)
    instance: int = -1  # instance mode: the instance within its weather (sweep: within the set)
    in_window: bool = False  # instance mode: a 10 Hz frame of the decision window


def row_columns(cfg) -> tuple[str, ...]:
    """meta/frames.csv's columns: instance mode (cfg.space set) appends INSTANCE_COLUMNS, a bounds set also
    ``simulator.bounds.PROBE_COLUMNS``."""
    probes = PROBE_COLUMNS if cfg.space is not None and cfg.space.probes else ()
    return ROW_COLUMNS + (INSTANCE_COLUMNS if cfg.space is not None else ()) + probes


def job_instance(cfg, job: FrameJob) -> Instance:
    """The scenario instance an instance-mode frame belongs to."""
    return instances(cfg.space, cfg.seed)[job.instance]


def job_weather(cfg, job: FrameJob) -> WeatherPreset:
    """The frame's weather: its preset, or in the sweep set its instance's point."""
    if job.weather == SWEEP_WEATHER:
        return sweep_weather(sweep_points(cfg.space, cfg.seed)[job.instance])
    return WEATHER_PRESETS[job.weather]


def instance_run(cfg, index: int) -> list[FrameState]:
    """Every step of instance ``index``'s run (cached per process); its background traffic is the study's for
    SOTIF instance 0 and its own stream otherwise."""
    key = (cfg.road, cfg.sotif, cfg.space, cfg.seed, index)
    if key not in _RUNS:
        inst = instances(cfg.space, cfg.seed)[index]
        sc = inst.sotif_config(cfg.sotif)
        stream = [cfg.seed, 21] if (index == 0 and not cfg.space.sweep) else [cfg.seed, 21 + 2 * cfg.space.sweep, index]
        if cfg.space.probes:  # a reference scenario's traffic, whatever the probe
            stream = [cfg.seed, STREAM_TAG, *cfg.space.probes[index].held_key()]
        n = run_steps(sc, cfg.space.window_max_s, cfg.space.window_slack_s)
        if len(_RUNS) >= 512:  # a run is ~100 small FrameStates
            _RUNS.pop(next(iter(_RUNS)))
        _RUNS[key] = sotif_run(cfg.road, n, np.random.default_rng(stream), replace(sc, record_every=1),
                               inst.lateral_offset_m, inst.slow_reflectance)
    return _RUNS[key]


def world_scene(cfg, job: FrameJob) -> RayScene:
    """Cached Embree scene of the world this frame lives in."""
    variant = 0 if cfg.preset != "train" else job.index // TRAIN_FRAMES_PER_WORLD
    key = (cfg.road, cfg.seed, cfg.preset, variant)
    if key not in _SCENES:
        if len(_SCENES) >= 2:
            _SCENES.pop(next(iter(_SCENES)))
        rng = np.random.default_rng([cfg.seed, WORLD_TAG[cfg.preset], variant])
        _SCENES[key] = RayScene(build_world(cfg.road, rng))
    return _SCENES[key]


def frame_state(cfg, job: FrameJob) -> FrameState:
    if cfg.space is not None:
        return instance_run(cfg, job.instance)[job.step]
    if cfg.preset == "sotif":
        key = (cfg.road, cfg.sotif, cfg.seed, job.run_length)
        if key not in _RUNS:
            n = max(job.run_length, MIN_RUN_FRAMES)
            _RUNS[key] = sotif_run(cfg.road, n, np.random.default_rng([cfg.seed, 21]), cfg.sotif)
        return _RUNS[key][job.step]
    return training_scene(cfg.road, np.random.default_rng([cfg.seed, 22, job.index]), cfg.train)


def surface_ranges(scene: RayScene, pose: Pose, mount_height: float, points: np.ndarray) -> np.ndarray:
    """Range of the first surface along each point's ray for the points a phantom return can be
    (fidelity.AIR_RANGE_M, above the road plane; NaN: not cast, inf: no surface); vehicles as scanned."""
    r = np.linalg.norm(points[:, :3].astype(np.float64), axis=1)
    cast = np.flatnonzero((r < fidelity.AIR_RANGE_M) & (points[:, 2] > 0.15 - mount_height) & (r > 0))
    out = np.full(len(points), np.nan)
    if len(cast):
        dirs = points[cast, :3].astype(np.float64) / r[cast, None]
        t = scene.cast(np.array([pose.x, pose.y, mount_height]), dirs @ pose.rotation().T).t
        out[cast] = np.where(t < 1e30, t, np.inf)
    return out


def _fidelity(scene: RayScene, cfg, state: FrameState, points: np.ndarray, weather) -> dict:
    slow = [i for i, v in enumerate(state.vehicles) if v.role == "slow"]
    box = lidar_boxes(state.vehicles, state.pose, cfg.lidar.mount_height)[slow[0]] if slow else None
    return fidelity.frame_fidelity(points, box, surface_ranges(scene, state.pose, cfg.lidar.mount_height, points),
                                   weather)


def _instance_row(cfg, job: FrameJob, p: WeatherPreset) -> dict:
    """The INSTANCE_COLUMNS of an instance-mode frame."""
    axis = sweep_points(cfg.space, cfg.seed)[job.instance].axis if job.weather == SWEEP_WEATHER else "preset"
    return {"instance": job.instance, "instance_key": f"{job.weather}#{job.instance}", "sweep_axis": axis,
            "fog_mor_m": round(p.lidar_fog_mor_m, 4), "road_water": round(road_water_cover(p), 4),
            "in_window": int(job.in_window), **job_instance(cfg, job).columns(),
            **(cfg.space.probes[job.instance].columns() if cfg.space.probes else {})}


def _row(cfg, job: FrameJob, state: FrameState, n_points: int, rows: np.ndarray, p: WeatherPreset) -> dict:
    roles = [v.role for v in state.vehicles]
    idx = {r: int(rows[roles.index(r)]) if r in roles else -1 for r in ("slow", "fast")}
    return {
        "frame_id": job.frame_id, "split": job.split, "scenario": cfg.preset, "weather": job.weather,
        "time_of_day": time_of_day(p), "precipitation_class": precipitation_class(p),
        "cloudiness": p.cloudiness, "precipitation": p.precipitation,
        "precipitation_deposits": p.precipitation_deposits, "wetness": p.wetness,
        "fog_density": p.fog_density, "fog_distance": p.fog_distance, "wind_intensity": p.wind_intensity,
        "sun_altitude_angle": p.sun_altitude_angle, "rain_rate_mmh": rain_rate_mmh(p),
        "scenario_time_s": round(state.time_s, 3), "ego_speed_mps": round(state.ego_speed, 4),
        "slow_car_speed_mps": _num(state.info["slow_car_speed_mps"]),
        "lane_change_time_s": _num(state.info["lane_change_time_s"]),
        "cutout_time_s": _num(state.info.get("cutout_time_s", float("nan"))),
        "slow_car_label_index": idx["slow"], "fast_car_label_index": idx["fast"],
        "slow_car_distance_m": _num(state.info["slow_car_distance_m"]), "n_points": n_points,
        "n_vehicles": len(state.vehicles), "lidar_model": cfg.lidar.model,
    } | (_instance_row(cfg, job, p) if cfg.space is not None else {})


def _num(v: float) -> float | None:
    return None if v is None or (isinstance(v, float) and math.isnan(v)) else round(float(v), 4)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def encode_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an (H, W, 3) uint8 image: 8-bit RGB, every row with the Up filter, zlib level 1,
    no metadata. (Pillow tries all five filters on every row, which costs more than the compression;
    the rendered images are smooth vertically, so Up alone compresses better and twice as fast.)"""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"encode_png: expected an (H, W, 3) image, got shape {rgb.shape}")
    h, w, _ = rgb.shape
    rows = np.empty((h, 1 + 3 * w), np.uint8)
    rows[:, 0] = 2  # filter type Up: byte minus the byte above (mod 256)
    flat = rgb.reshape(h, 3 * w)
    rows[0, 1:] = flat[0]
    np.subtract(flat[1:], flat[:-1], out=rows[1:, 1:])
    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)  # 8 bit, RGB, deflate, adaptive filtering, no interlace
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", header)
            + _png_chunk(b"IDAT", zlib.compress(rows.tobytes(), 1)) + _png_chunk(b"IEND", b""))


def make_frame(root: Path, cfg, job: FrameJob) -> tuple[dict, list[Path]]:
    """Simulate and write one frame; returns its meta row and the files written."""
    scene = world_scene(cfg, job)
    state = frame_state(cfg, job)
    weather = job_weather(cfg, job)
    scene.set_vehicles(state.vehicles)
    lidar_key = [job.step] if cfg.preset == "sotif" else [job.index]
    camera_key = [job.index]
    if cfg.space is not None:  # the same instance's step scans alike in every weather
        lidar_key = [job.instance, job.step]
    if cfg.space is not None and cfg.space.probes:  # a probe's streams: its reference scenario, noise seed, step
        probe = cfg.space.probes[job.instance]
        lidar_key = camera_key = [*probe.held_key(), probe.noise_seed, job.step]
    points = scan(scene, cfg.lidar, state.pose, weather, state.vehicles,
                  np.random.default_rng([cfg.seed, SCENARIO_TAG[cfg.preset], 1, *lidar_key]))
    calib = kitti.kitti_calib(cfg.camera.width, cfg.camera.height)
    image = render(scene, calib.lidar2img(), state.pose, cfg.lidar.mount_height, weather,
                   np.random.default_rng([cfg.seed, SCENARIO_TAG[cfg.preset], 2, *camera_key]), cfg.camera)
    labels, rows = frame_labels(scene, state.vehicles, state.pose, cfg.lidar.mount_height, calib, cfg.labels)
    files = [kitti.write_points(kitti.frame_path(root, "velodyne", job.frame_id), points),
             atomic_write_bytes(kitti.frame_path(root, "image_2", job.frame_id), encode_png(image)),
             kitti.write_calib(kitti.frame_path(root, "calib", job.frame_id), calib),
             kitti.write_labels(kitti.frame_path(root, "label_2", job.frame_id), labels)]
    return {**_row(cfg, job, state, len(points), rows, weather), **_fidelity(scene, cfg, state, points, weather)}, files
