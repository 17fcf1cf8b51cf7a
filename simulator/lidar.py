"""Spinning LiDAR: ray pattern from a spec, first return, intensity and weather effects.

Physics mode: received power rho cos(theta) T^2 / r^2 of the first surface hit, detected when
above the power a `detect_reflectivity` Lambertian target returns at `max_range`; range noise;
then the weather's soft returns (raindrops, fog, spray, sunlight) replace the hard return
when they come first. CARLA mode reproduces CARLA's ray-cast LiDAR, which ignores weather.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from functools import lru_cache

import numba
import numpy as np

from simulator import effects
from simulator.materials import GROUND, REFLECTIVITY
from simulator.raycast import RayScene
from simulator.vehicles import Vehicle
from simulator.weather import WeatherPreset, fog_extinction, rain_rate_mmh, road_water_cover


def hdl64e_elevations() -> tuple[float, ...]:
    """HDL-64E-like channel elevations (deg): upper block 1/3 deg steps, lower block ~1/2 deg."""
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.83, -24.8, 32)
    return tuple(float(round(e, 4)) for e in np.concatenate([upper, lower]))


@dataclass(frozen=True)
class LidarSpec:
    name: str = "HDL-64E"
    elevations_deg: tuple[float, ...] = field(default_factory=hdl64e_elevations)  # channels, top first
    azimuth_step_deg: float = 0.17
    max_range: float = 120.0  # m
    min_range: float = 1.0  # m
    mount_height: float = 1.73  # m above the road
    range_noise_m: float = 0.02  # 1 sigma, every return
    detect_reflectivity: float = 0.02  # weakest normal-incidence target seen at max_range
    rain_range_noise: float = 0.02  # Goodin et al.: sigma = k r (1 - exp(-R))^2
    model: str = "physics"  # "physics" or "carla"

    @property
    def n_azimuth(self) -> int:
        return int(round(360.0 / self.azimuth_step_deg))

    @property
    def min_power(self) -> float:
        return self.detect_reflectivity / self.max_range ** 2

    def as_dict(self) -> dict:
        return asdict(self)


def carla_spec(base: LidarSpec | None = None) -> LidarSpec:
    """CARLA's ray-cast LiDAR with the same FOV: uniform elevations, no noise, weather-blind."""
    base = base or LidarSpec()
    el = np.linspace(max(base.elevations_deg), min(base.elevations_deg), len(base.elevations_deg))
    return replace(base, name="CARLA-ray_cast", elevations_deg=tuple(float(e) for e in el),
                   range_noise_m=0.0, model="carla")


@lru_cache(maxsize=8)
def ray_directions(spec: LidarSpec) -> np.ndarray:
    """(C * A, 3) unit directions in the LiDAR frame, channel-major, azimuth from +x CCW."""
    el = np.deg2rad(np.asarray(spec.elevations_deg))[:, None]
    az = (np.arange(spec.n_azimuth) * 2 * np.pi / spec.n_azimuth)[None, :]
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)], -1)
    return d.reshape(-1, 3)


@dataclass
class Pose:
    """Ego pose: world position of the point on the road under the LiDAR, heading (rad)."""

    x: float
    y: float
    yaw: float

    def rotation(self) -> np.ndarray:
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def to_lidar(self, pts_world: np.ndarray, mount_height: float) -> np.ndarray:
        """World points (N, 3) -> LiDAR frame."""
        return (np.asarray(pts_world) - [self.x, self.y, mount_height]) @ self.rotation()


def detection_range(spec: LidarSpec, weather: WeatherPreset, reflectivity: float = 0.1) -> float:
    """Largest range (m) at which a normal-incidence Lambertian target is still detected."""
    a_rain = effects.marshall_palmer_extinction(rain_rate_mmh(weather))
    a_fog = fog_extinction(weather)
    r = np.linspace(spec.min_range, spec.max_range, 20001)
    t2 = effects.two_way_transmission(r, a_rain, a_fog, weather.fog_distance)
    ok = effects.received_power(reflectivity, 1.0, r, t2) >= spec.min_power
    return float(r[ok].max()) if ok.any() else 0.0


def rotate_yaw(v: np.ndarray, yaw: float) -> np.ndarray:
    """Rotate vectors (N, 3) by yaw about +z (column arithmetic, faster than a (3, 3) matmul)."""
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.empty_like(v)
    out[:, 0] = c * v[:, 0] - s * v[:, 1]
    out[:, 1] = s * v[:, 0] + c * v[:, 1]
    out[:, 2] = v[:, 2]
    return out


def cast_pattern(scene: RayScene, spec: LidarSpec, pose: Pose):
    """Hits of the full scan pattern: (unit dirs in the LiDAR frame, in the world, hits)."""
    dirs = ray_directions(spec)
    world_dirs = rotate_yaw(dirs, pose.yaw)
    hits = scene.cast(np.array([pose.x, pose.y, spec.mount_height]), world_dirs)
    return dirs, world_dirs, hits


def scan(scene: RayScene, spec: LidarSpec, pose: Pose, weather: WeatherPreset,
         vehicles: list[Vehicle], rng: np.random.Generator) -> np.ndarray:
    """One scan: (N, 4) float32 x, y, z, intensity in the LiDAR frame (scene vehicles set)."""
    dirs, world_dirs, hits = cast_pattern(scene, spec, pose)
    if spec.model == "carla":
        r, inten = carla_returns(hits.t, spec, rng)
    else:
        r, inten = physics_returns(dirs, world_dirs, hits, spec, pose, weather, vehicles, rng)
    ok = np.flatnonzero(np.isfinite(r))
    out = np.empty((len(ok), 4), np.float32)
    out[:, :3] = dirs[ok] * r[ok, None]
    out[:, 3] = inten[ok]
    return out


def carla_returns(t: np.ndarray, spec: LidarSpec, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """CARLA: range-only intensity exp(-0.004 d) and its drop-off model; NaN = no point."""
    inten = effects.carla_intensity(np.where(np.isfinite(t), t, 0.0))
    keep = effects.carla_keep(inten, rng) & (t <= spec.max_range)
    return np.where(keep, t, np.nan), inten


@numba.njit(cache=True)
def hard_returns(t, normal, dirs, material, refl_table, ground_table, cover, a_rain, a_fog, fog_start,
                 min_power, min_range, max_range, sigma0, goodin_k, noise):
    """Surface returns of N rays, fused: range with noise (NaN = lost) and intensity.

    Same formulas as simulator.effects: wet_reflectivity on ground materials, two-way
    transmission, received power against min_power, range sigma hypot(sigma0, goodin_k r),
    intensity rho cos(theta) T^2 exp(-0.004 r).
    """
    n = t.shape[0]
    r_out = np.full(n, np.nan)
    i_out = np.zeros(n)
    for i in range(n):
        r = t[i]
        if not (r >= min_range and r <= max_range):
            continue
        cos_i = -(normal[i, 0] * dirs[i, 0] + normal[i, 1] * dirs[i, 1] + normal[i, 2] * dirs[i, 2])
        cos_i = min(max(cos_i, 1e-3), 1.0)
        rho = refl_table[material[i]]
        if cover > 0 and ground_table[material[i]]:
            sin_t = np.sqrt(1.0 - cos_i * cos_i) / effects.WATER_INDEX
            cos_t = np.sqrt(max(1.0 - sin_t * sin_t, 0.0))
            nw = effects.WATER_INDEX
            rs = (cos_i - nw * cos_t) / (cos_i + nw * cos_t)
            rp = (cos_t - nw * cos_i) / (cos_t + nw * cos_i)
            fres = 0.5 * (rs * rs + rp * rp)
            rho = rho * (1.0 - effects.WET_DARKENING * cover) * ((1.0 - cover) + cover * (1.0 - fres) ** 2)
        t2 = np.exp(-2.0 * a_rain * r - 2.0 * a_fog * max(r - fog_start, 0.0))
        if rho * cos_i * t2 / (r * r) < min_power:
            continue
        r_out[i] = r + noise[i] * np.sqrt(sigma0 * sigma0 + (goodin_k * r) ** 2)
        i_out[i] = min(max(rho * cos_i * t2 * np.exp(-effects.CARLA_ATTENUATION * r), 0.0), 1.0)
    return r_out, i_out


def physics_returns(dirs: np.ndarray, world_dirs: np.ndarray, hits, spec: LidarSpec, pose: Pose,
                    weather: WeatherPreset, vehicles: list[Vehicle],
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Physics mode ranges (NaN = no point) and intensities of all rays."""
    n = len(dirs)
    cover = road_water_cover(weather)
    rain = rain_rate_mmh(weather)
    a_rain, a_fog = effects.marshall_palmer_extinction(rain), fog_extinction(weather)
    r_out, i_out = hard_returns(hits.t, hits.normal, world_dirs, hits.material, REFLECTIVITY.astype(np.float64),
                                GROUND, cover, a_rain, a_fog, weather.fog_distance, spec.min_power,
                                spec.min_range, spec.max_range, spec.range_noise_m,
                                float(effects.goodin_range_sigma(1.0, rain, spec.rain_range_noise)),
                                rng.standard_normal(n))
    hard_or_far = np.where(np.isfinite(r_out), r_out, spec.max_range)
    soft = np.full(n, np.inf)
    soft_i = np.zeros(n)
    sources = []
    if a_rain > 0:
        sources.append((effects.rain_backscatter(hard_or_far, a_rain, rng), 0.02))
    if a_fog > 0:
        sources.append((effects.fog_backscatter(hard_or_far, a_fog, rng), 0.03))
    sources.append((effects.sunlight_noise(n, weather.sun_altitude_angle, weather.cloudiness, spec.max_range, rng), 0.01))
    if cover > 0:
        sources.append((spray_ranges(dirs, spec, pose, vehicles, cover, rng), 0.05))
    for rs, level in sources:
        nearer = rs < soft  # NaN compares False
        soft[nearer] = rs[nearer]
        soft_i[nearer] = level
    use_soft = soft < np.nan_to_num(r_out, nan=np.inf)
    r_out[use_soft] = soft[use_soft]
    i_out[use_soft] = soft_i[use_soft] * rng.uniform(0.5, 1.5, int(use_soft.sum()))
    r_out[(r_out < spec.min_range) | (r_out > spec.max_range)] = np.nan
    return r_out, i_out


def spray_ranges(dirs: np.ndarray, spec: LidarSpec, pose: Pose, vehicles: list[Vehicle], cover: float,
                 rng: np.random.Generator) -> np.ndarray:
    """Per-ray range of a spray droplet cluster (NaN for none), clusters snapped to the nearest ray."""
    out = np.full(len(dirs), np.nan)
    if cover <= 0 or not vehicles:
        return out
    centres = np.array([[v.x, v.y, 0.0] for v in vehicles])
    pts = effects.spray_cloud(centres, np.array([v.heading for v in vehicles]),
                              np.array([v.dims for v in vehicles]), np.array([v.speed for v in vehicles]),
                              cover, rng)
    if len(pts) == 0:
        return out
    local = pose.to_lidar(pts, spec.mount_height)
    rng_ = np.linalg.norm(local, axis=1)
    el = np.rad2deg(np.arcsin(local[:, 2] / np.maximum(rng_, 1e-6)))
    az = np.arctan2(local[:, 1], local[:, 0]) % (2 * np.pi)
    elev = np.asarray(spec.elevations_deg)
    ch = np.abs(el[:, None] - elev[None]).argmin(1)
    close = np.abs(el - elev[ch]) < 0.2
    col = np.round(az / (2 * np.pi) * spec.n_azimuth).astype(int) % spec.n_azimuth
    idx = ch * spec.n_azimuth + col
    nearest = np.full(len(dirs), np.inf)
    np.minimum.at(nearest, idx[close], rng_[close])
    out[np.isfinite(nearest)] = nearest[np.isfinite(nearest)]
    return out
