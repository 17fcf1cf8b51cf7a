"""Spinning LiDAR: ray pattern from a spec, first return, intensity and weather effects.

Physics mode: received power rho cos(theta) T^2 / r^2 of the first surface hit, detected when
at least the spec's P_min (the weakest Lambertian target of `detection_spec`); range noise from the
signal (LISA); the strongest of target, raindrop, fog and spray returns (the HDL-64E's strongest-return
mode, as LISA and Hahner et al.); then a sunlight false trigger replaces it when it comes first. CARLA mode reproduces CARLA's ray-cast LiDAR, which ignores weather.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from functools import lru_cache

import numba
import numpy as np

from simulator import effects
from simulator.raycast import RayScene
from simulator.vehicles import Vehicle
from simulator.weather import WeatherPreset, lidar_fog_extinction, rain_rate_mmh, road_water_cover
from simulator.ziggurat import normals


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
    range_noise_m: float = 0.02  # 1 sigma floor, every return (HDL-64E: < 2 cm)
    # (reflectivity, range m) of Lambertian targets the sensor detects (HDL-64E: pavement 10 % at 50 m,
    # cars and foliage 80 % at 120 m); P_min is the weakest of them
    detection_spec: tuple[tuple[float, float], ...] = ((0.10, 50.0), (0.80, 120.0))
    range_accuracy_m: float = 0.04  # LISA's dR in sigma = dR / sqrt(2 SNR)
    beam_divergence_rad: float = 3e-3  # full angle (LISA)
    pulse_half_power_s: float = 20e-9  # tau_H of the sin^2 pulse (Hahner et al.)
    model: str = "physics"  # "physics" or "carla"

    @property
    def n_azimuth(self) -> int:
        return int(round(360.0 / self.azimuth_step_deg))

    @property
    def min_power(self) -> float:
        return effects.spec_min_power(self.detection_spec)

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
    a_fog = lidar_fog_extinction(weather)
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


@numba.njit(cache=True)
def world_rays(dirs: np.ndarray, yaw: float, origin: np.ndarray):
    """Pattern rays in the world as Embree takes them: float32 dirs rotated by yaw, float32 origins (N, 3)."""
    c, s = np.cos(yaw), np.sin(yaw)
    n = dirs.shape[0]
    wd32 = np.empty((n, 3), np.float32)
    o32 = np.empty((n, 3), np.float32)
    ox, oy, oz = np.float32(origin[0]), np.float32(origin[1]), np.float32(origin[2])
    for i in range(n):
        wd32[i, 0] = c * dirs[i, 0] - s * dirs[i, 1]
        wd32[i, 1] = s * dirs[i, 0] + c * dirs[i, 1]
        wd32[i, 2] = dirs[i, 2]
        o32[i, 0], o32[i, 1], o32[i, 2] = ox, oy, oz
    return wd32, o32


@numba.njit(cache=True)
def pattern_rays_near_spheres(origin, dirs, n_az, yaw, centres, radii):
    """raycast.rays_near_spheres for the scan pattern (channel-major, azimuth c * 2 pi / n_az + yaw).

    A ray passing within r of a centre has its horizontal projection within r of the centre's
    projection, so only azimuth columns within asin(r / horizontal distance) (plus one column
    of margin) of the centre's azimuth are tested, with the same exact test.
    """
    n = dirs.shape[0]
    n_ch = n // n_az
    step = 2.0 * np.pi / n_az
    out = np.zeros(n, dtype=np.bool_)
    for j in range(centres.shape[0]):
        cx = centres[j, 0] - origin[0]
        cy = centres[j, 1] - origin[1]
        cz = centres[j, 2] - origin[2]
        rad = radii[j]
        rho = np.sqrt(cx * cx + cy * cy)
        lo, hi = 0, n_az - 1
        if rho > rad:
            mid = (np.arctan2(cy, cx) - yaw) / step
            half = np.arcsin(rad / rho) / step
            lo, hi = int(np.floor(mid - half)) - 1, int(np.ceil(mid + half)) + 1
            if hi - lo + 1 >= n_az:
                lo, hi = 0, n_az - 1
        for col in range(lo, hi + 1):
            for ch in range(n_ch):
                i = ch * n_az + col % n_az
                if out[i]:
                    continue
                along = cx * dirs[i, 0] + cy * dirs[i, 1] + cz * dirs[i, 2]
                if along < -rad:
                    continue
                if cx * cx + cy * cy + cz * cz - along * along <= rad * rad:
                    out[i] = True
    return out


def scan(scene: RayScene, spec: LidarSpec, pose: Pose, weather: WeatherPreset,
         vehicles: list[Vehicle], rng: np.random.Generator) -> np.ndarray:
    """One scan: (N, 4) float32 x, y, z, intensity in the LiDAR frame (scene vehicles set)."""
    dirs = ray_directions(spec)
    origin = np.array([pose.x, pose.y, spec.mount_height])
    world_dirs, o32 = world_rays(dirs, pose.yaw, origin)
    if spec.model == "carla":
        r, inten = carla_returns(scene.cast(origin, world_dirs).t, spec, rng)
        return points_from_returns(dirs, r, inten, 0.0, np.inf)
    near = np.zeros(0, np.int64)
    if scene.vehicles:
        near = np.flatnonzero(pattern_rays_near_spheres(origin, world_dirs, spec.n_azimuth, pose.yaw, *scene.spheres))
    st, dy = scene.cast_parts(o32, world_dirs, near, spec.max_range)  # farther surfaces return nothing
    r, inten = physics_returns(st, near, dy, scene, world_dirs, spec, pose, weather, vehicles, rng)
    return points_from_returns(dirs, r, inten, spec.min_range, spec.max_range)


@numba.njit(cache=True)
def points_from_returns(dirs, r, inten, min_range, max_range):
    """(M, 4) float32 points of the rays whose range lies in [min_range, max_range] (NaN: none)."""
    m = 0
    for i in range(r.shape[0]):
        if r[i] >= min_range and r[i] <= max_range:
            m += 1
    out = np.empty((m, 4), np.float32)
    k = 0
    for i in range(r.shape[0]):
        if r[i] >= min_range and r[i] <= max_range:
            for a in range(3):
                out[k, a] = dirs[i, a] * r[i]
            out[k, 3] = inten[i]
            k += 1
    return out


def carla_returns(t: np.ndarray, spec: LidarSpec, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """CARLA: range-only intensity exp(-0.004 d) and its drop-off model; NaN = no point."""
    inten = effects.carla_intensity(np.where(np.isfinite(t), t, 0.0))
    keep = effects.carla_keep(inten, rng) & (t <= spec.max_range)
    return np.where(keep, t, np.nan), inten


@numba.njit(cache=True, inline="always", error_model="numpy")
def wet_rho(rho, cos_i, cover):
    """effects.wet_reflectivity of one hit (cos_i in [1e-3, 1]) with the Fresnel terms sharing one division."""
    nw = effects.WATER_INDEX  # Fresnel: rs = a / b, rp = c / d
    cos_t = np.sqrt(max(1.0 - (1.0 - cos_i * cos_i) * (1.0 / (nw * nw)), 0.0))
    a, b = cos_i - nw * cos_t, cos_i + nw * cos_t
    c, d = cos_t - nw * cos_i, cos_t + nw * cos_i
    fres = 0.5 * (a * a * d * d + c * c * b * b) / (b * b * d * d)
    return rho * (1.0 - effects.WET_DARKENING * cover) * ((1.0 - cover) + cover * (1.0 - fres) ** 2)


@numba.njit(cache=True)
def surface_return(r, cos_i, rho, ground, cover, a_rain, a_fog, fog_start, min_power, min_range, max_range):
    """(range or NaN when lost, intensity) of one surface hit before range noise.

    Same formulas as simulator.effects: wet_reflectivity on ground materials, two-way
    transmission, received power against min_power, intensity rho cos(theta) T^2 exp(-0.004 r).
    """
    if not (r >= min_range and r <= max_range):
        return np.nan, 0.0
    cos_i = min(max(cos_i, 1e-3), 1.0)
    if cover > 0 and ground:
        rho = wet_rho(rho, cos_i, cover)
    t2 = np.exp(-2.0 * a_rain * r - 2.0 * a_fog * max(r - fog_start, 0.0))
    if rho * cos_i * t2 < min_power * (r * r):
        return np.nan, 0.0
    return r, min(max(rho * cos_i * t2 * np.exp(-effects.CARLA_ATTENUATION * r), 0.0), 1.0)


@numba.njit(cache=True)
def hard_returns(t, normal, dirs, material, refl_table, ground_table, cover, a_rain, a_fog, fog_start,
                 min_power, min_range, max_range):
    """Surface returns of N merged hits (raycast.Hits): range before noise (NaN = lost), intensity.

    The reference for first_returns, which does the same straight from Embree's output."""
    n = t.shape[0]
    r_out = np.empty(n)
    i_out = np.empty(n)
    for i in range(n):
        cos_i = -(normal[i, 0] * dirs[i, 0] + normal[i, 1] * dirs[i, 1] + normal[i, 2] * dirs[i, 2])
        m = material[i]
        r_out[i], i_out[i] = surface_return(t[i], cos_i, refl_table[m], ground_table[m], cover, a_rain, a_fog,
                                            fog_start, min_power, min_range, max_range)
    return r_out, i_out


@numba.njit(cache=True, error_model="numpy")  # numpy error model: divisions carry no zero check and vectorise
def first_returns(t_s, prim_s, ng_s, mat_s, near, t_d, prim_d, ng_d, mat_d, dirs, refl_table, ground_table,
                  cover, a_rain, a_fog, fog_start, min_power, min_range, max_range):
    """raycast.merge_hits and hard_returns over Embree's raw output, in three loops.

    Static hits (t_s, prim_s, ng_s) of all N rays, vehicle hits (t_d, prim_d, ng_d) of the rays
    `near` (sorted). Returns ranges before noise (N,) (NaN = lost), intensities (N,), the sorted
    indices of the detected rays, the free path of every ray (N,) (its surface's range, max_range
    when none is nearer) and the received power of the detected rays (N,) (NaN = lost). The loops: (1) the nearer hit in range -> compact
    (ray, r, |n . d|, |n|^2, rho, ground) lists, (2) cos(theta) and wet_rho on the ground hits
    (branch-free, so they vectorise), (3) transmission, power threshold and intensity (the same
    decisions as surface_return; intensities within a few ulp, as T^2 exp(-0.004 r) is one exp).
    """
    n = t_s.shape[0]
    r_out = np.full(n, np.nan)
    i_out = np.zeros(n)
    path = np.full(n, max_range)
    p_out = np.full(n, np.nan)
    ray, rr, cs, n2, rho = np.empty(n, np.int64), np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    gnd = np.empty(n, np.bool_)
    k, j = 0, 0
    for i in range(n):
        t, m = np.inf, -1
        nx, ny, nz = 0.0, 0.0, 0.0
        if prim_s[i] >= 0:
            t, m = float(t_s[i]), mat_s[prim_s[i]]
            nx, ny, nz = float(ng_s[i, 0]), float(ng_s[i, 1]), float(ng_s[i, 2])
        if j < near.shape[0] and near[j] == i:
            if prim_d[j] >= 0 and t_d[j] < t:
                t, m = float(t_d[j]), mat_d[prim_d[j]]
                nx, ny, nz = float(ng_d[j, 0]), float(ng_d[j, 1]), float(ng_d[j, 2])
            j += 1
        if m >= 0:
            path[i] = min(t, max_range)
        if m >= 0 and t >= min_range and t <= max_range:
            ray[k], rr[k], rho[k], gnd[k] = i, t, refl_table[m], ground_table[m]
            cs[k], n2[k] = abs(nx * dirs[i, 0] + ny * dirs[i, 1] + nz * dirs[i, 2]), nx * nx + ny * ny + nz * nz
            k += 1
    for q in range(k):  # |n . d| / |n|, 0 for a degenerate triangle, clipped to [1e-3, 1]
        cos_i = cs[q] / np.sqrt(n2[q])
        cs[q] = min(max(cos_i if n2[q] > 0 else 0.0, 1e-3), 1.0)
    if cover > 0:
        for q in range(k):
            wet = wet_rho(rho[q], cs[q], cover)
            rho[q] = wet if gnd[q] else rho[q]
    # One exp per hit: e = T^2 exp(-0.004 r) gives the intensity, and as T^2 / e = exp(0.004 r) lies in
    # [1, exp(0.004 max_range)], it settles the power test (rho cos T^2 >= min_power r^2) except in a
    # narrow band around the threshold, where T^2 itself is computed.
    band = np.exp(effects.CARLA_ATTENUATION * max_range) * (1.0 + 1e-12)
    m = 0
    for q in range(k):
        r = rr[q]
        depth = 2.0 * a_rain * r + 2.0 * a_fog * max(r - fog_start, 0.0)  # two-way optical depth
        p_i = rho[q] * cs[q] * np.exp(-depth - effects.CARLA_ATTENUATION * r)
        need = min_power * (r * r)
        if p_i < need * (1.0 + 1e-12):
            if p_i * band < need or rho[q] * cs[q] * np.exp(-depth) < need:
                continue
        i = ray[q]
        r_out[i], i_out[i] = r, min(max(p_i, 0.0), 1.0)
        p_out[i] = rho[q] * cs[q] * np.exp(-depth) / (r * r)
        ray[m] = i
        m += 1
    return r_out, i_out, ray[:m], path, p_out


@numba.njit(cache=True, error_model="numpy")
def add_range_noise(r, hit, z, power, p_min, sigma0, range_accuracy):
    """Range noise on the detected rays `hit` in place: r[hit] += z * sigma, sigma = effects.lisa_range_sigma
    of each ray's received power (z (M,) standard normals)."""
    for q in range(hit.shape[0]):
        i = hit[q]
        r[i] += z[q] * np.sqrt(sigma0 * sigma0 + range_accuracy * range_accuracy * p_min / (2.0 * power[i]))


def physics_returns(st: dict, near: np.ndarray, dy: dict, scene: RayScene, world_dirs: np.ndarray,
                    spec: LidarSpec, pose: Pose, weather: WeatherPreset, vehicles: list[Vehicle],
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Physics mode ranges (NaN = no point) and intensities of all rays from Embree's output."""
    n = len(world_dirs)
    cover = road_water_cover(weather)
    rain = rain_rate_mmh(weather)
    a_rain, a_fog, fog_start = effects.marshall_palmer_extinction(rain), lidar_fog_extinction(weather), weather.fog_distance
    p_min = spec.min_power
    r_out, i_out, hit, path, power = first_returns(
        st["tfar"], st["primID"], st["Ng"], scene.static_material, near, dy["tfar"], dy["primID"], dy["Ng"],
        scene.lidar_dyn_material, world_dirs, scene.lidar_reflectivity, scene.lidar_ground, cover, a_rain, a_fog,
        fog_start,
        p_min, spec.min_range, spec.max_range)
    add_range_noise(r_out, hit, normals(rng, len(hit)), power, p_min, spec.range_noise_m, spec.range_accuracy_m)
    for idx, soft, p_soft in (
            effects.rain_drop_returns(path, rain, a_rain, p_min, spec.min_range, spec.beam_divergence_rad, rng),
            effects.fog_returns(path, a_fog, fog_start, spec.pulse_half_power_s, p_min, spec.max_range),
            spray_returns(spec, pose, vehicles, cover, path, a_rain, rng)):
        stronger = (p_soft >= p_min) & ~(power[idx] >= p_soft)  # the target is lost (NaN) or weaker: strongest
        idx, soft, p_soft = idx[stronger], soft[stronger], p_soft[stronger]
        noise = normals(rng, len(idx)) * effects.lisa_range_sigma(p_soft, p_min, spec.range_accuracy_m, spec.range_noise_m)
        r_out[idx], power[idx] = soft + noise, p_soft
        i_out[idx] = np.minimum(p_soft * soft ** 2 * np.exp(-effects.CARLA_ATTENUATION * soft), 1.0)
    idx, soft = effects.sunlight_noise(n, weather.sun_altitude_angle, weather.cloudiness, spec.max_range, rng)
    use = soft < np.where(np.isnan(r_out[idx]), np.inf, r_out[idx])  # a false trigger before the echo: first return
    r_out[idx[use]] = soft[use]
    i_out[idx[use]] = SUNLIGHT_LEVEL * rng.uniform(0.5, 1.5, int(use.sum()))
    return r_out, i_out


SPRAY_REFLECTANCE = 0.05  # a spray cluster as a beam-filling soft target (not a published value)
SUNLIGHT_LEVEL = 0.01  # mean intensity of a sunlight false return


def spray_returns(spec: LidarSpec, pose: Pose, vehicles: list[Vehicle], cover: float, path: np.ndarray,
                  a_rain: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Spray clusters in front of their ray's surface as (sorted ray indices, ranges, received powers):
    SPRAY_REFLECTANCE T^2 / r^2, so spray competes with the target as the other soft returns do."""
    idx, r = spray_ranges(spec, pose, vehicles, cover, rng)
    front = r < path[idx]
    idx, r = idx[front], r[front]
    return idx, r, effects.received_power(SPRAY_REFLECTANCE, 1.0, r, effects.two_way_transmission(r, a_rain))


def spray_ranges(spec: LidarSpec, pose: Pose, vehicles: list[Vehicle], cover: float,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Spray droplet clusters snapped to their nearest ray: (sorted ray indices, nearest range per ray)."""
    none = (np.zeros(0, np.int64), np.zeros(0))
    if cover <= 0 or not vehicles:
        return none
    centres = np.array([[v.x, v.y, 0.0] for v in vehicles])
    pts = effects.spray_cloud(centres, np.array([v.heading for v in vehicles]),
                              np.array([v.dims for v in vehicles]), np.array([v.speed for v in vehicles]),
                              cover, rng)
    if len(pts) == 0:
        return none
    local = pose.to_lidar(pts, spec.mount_height)
    rng_ = np.linalg.norm(local, axis=1)
    el = np.rad2deg(np.arcsin(local[:, 2] / np.maximum(rng_, 1e-6)))
    az = np.arctan2(local[:, 1], local[:, 0]) % (2 * np.pi)
    elev = np.asarray(spec.elevations_deg)
    ch = np.abs(el[:, None] - elev[None]).argmin(1)
    close = np.abs(el - elev[ch]) < 0.2
    col = np.round(az / (2 * np.pi) * spec.n_azimuth).astype(int) % spec.n_azimuth
    idx, r = (ch * spec.n_azimuth + col)[close], rng_[close]
    first = effects.first_per_ray(idx, r)
    return idx[first].astype(np.int64), r[first]
