"""Front camera rendered by ray casting at a reduced resolution and upsampled.

Shading: Lambert sun light (direction from the preset's sun altitude) with ray-cast shadows,
sky ambient, emissive
head/tail lights, the ego's headlights at night, sky gradient with procedural clouds,
distance haze from fog and rain, wet-road sky reflections (Fresnel), rain darkening and
streaks. Rays come from the calibration's lidar2img, so any KITTI calib renders consistently.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from functools import lru_cache

import numpy as np
from PIL import Image, ImageDraw

from simulator import effects
from simulator.lidar import rotate_yaw
from simulator.materials import ALBEDO, EMISSION, ROAD
from simulator.raycast import RayScene
from simulator.weather import WeatherPreset, fog_extinction, rain_rate_mmh, road_water_cover, time_of_day

SUN_AZIMUTH = math.radians(150.0)  # world frame, CARLA's -1 means "unset"
SKY_HAZE_DISTANCE = 200.0  # m of haze in front of the sky
HEADLIGHT_RGB = np.array([1.0, 0.95, 0.8])
EMISSIVE = (EMISSION > 0).any(1)  # per material id
TAILLIGHT_RGB = np.array([1.0, 0.08, 0.04])


@dataclass(frozen=True)
class CameraSpec:
    width: int = 1242
    height: int = 375
    downsample: int = 3  # rays cast on a (height/downsample, width/downsample) grid

    def as_dict(self) -> dict:
        return asdict(self)


def camera_rays(lidar2img: np.ndarray, width: int, height: int, step: int):
    """Camera centre (3,) and unit ray directions (h, w, 3) in the LiDAR frame at pixel centres."""
    m = np.asarray(lidar2img, dtype=np.float64)[:3]
    inv = np.linalg.inv(m[:, :3])
    centre = -inv @ m[:, 3]
    u = (np.arange(width // step) + 0.5) * step - 0.5
    v = (np.arange(height // step) + 0.5) * step - 0.5
    uu, vv = np.meshgrid(u, v)
    pix = np.stack([uu, vv, np.ones_like(uu)], -1)
    d = pix @ inv.T
    return centre, d / np.linalg.norm(d, axis=-1, keepdims=True)


@lru_cache(maxsize=4)
def _rays_cached(key: bytes, width: int, height: int, step: int):
    return camera_rays(np.frombuffer(key).reshape(4, 4), width, height, step)


def sun_direction(p: WeatherPreset) -> np.ndarray:
    alt = math.radians(p.sun_altitude_angle)
    return np.array([math.cos(alt) * math.cos(SUN_AZIMUTH), math.cos(alt) * math.sin(SUN_AZIMUTH), math.sin(alt)])


def sky_colour(dirs: np.ndarray, p: WeatherPreset, seed_phase: np.ndarray) -> np.ndarray:
    """(N, 3) linear RGB of the sky in world directions, with clouds."""
    up = np.clip(dirs[:, 2], 0.0, 1.0)[:, None]
    tod = time_of_day(p)
    horizon, zenith = {"Noon": ((0.70, 0.78, 0.88), (0.22, 0.42, 0.80)),
                       "Sunset": ((0.95, 0.55, 0.30), (0.20, 0.25, 0.45)),
                       "Night": ((0.015, 0.018, 0.03), (0.004, 0.006, 0.015))}[tod]
    sky = np.array(horizon) * (1 - up) ** 2 + np.array(zenith) * (1 - (1 - up) ** 2)
    cover = p.cloudiness / 100.0
    u = dirs[:, 0] / np.maximum(dirs[:, 2], 0.05)
    v = dirs[:, 1] / np.maximum(dirs[:, 2], 0.05)
    noise = sum(np.sin(f * u + seed_phase[i]) * np.sin(f * 1.3 * v + seed_phase[i + 3]) / (i + 1)
                for i, f in enumerate((0.8, 1.9, 4.1)))
    clouds = np.clip((noise * 0.5 + 0.5) - (1.0 - cover) + 0.1, 0.0, 1.0)[:, None] * (dirs[:, 2:3] > 0)
    grey = {"Noon": 0.75, "Sunset": 0.55, "Night": 0.02}[tod] * (1.0 - 0.5 * p.precipitation / 100.0)
    return sky * (1 - clouds) + grey * clouds


def _light(p: WeatherPreset) -> tuple[float, float]:
    """(sun, ambient) intensities."""
    sun = max(0.0, math.sin(math.radians(p.sun_altitude_angle))) * (1.0 - 0.75 * p.cloudiness / 100.0)
    ambient = {"Noon": 0.45, "Sunset": 0.3, "Night": 0.015}[time_of_day(p)] * (1.0 - 0.3 * p.precipitation / 100.0)
    return 1.6 * sun ** 0.5 if sun > 0 else 0.0, ambient


def sun_visible(scene: RayScene, cam_w: np.ndarray, dirs_w: np.ndarray, hits, p: WeatherPreset) -> np.ndarray:
    """(N,) bool: the hit point sees the sun (shadow rays); all False when the sun is down."""
    sun = sun_direction(p)
    lit = np.isfinite(hits.t) & (hits.normal @ sun > 0) & (p.sun_altitude_angle > 0)
    idx = np.flatnonzero(lit)
    if len(idx) == 0:
        return lit
    pts = cam_w + dirs_w[idx] * hits.t[idx, None] + hits.normal[idx] * 0.02
    lit[idx] = ~scene.occluded(pts, np.broadcast_to(sun, pts.shape))
    return lit


def shade(hits, dirs_w: np.ndarray, lit: np.ndarray, ego_fwd: np.ndarray, p: WeatherPreset,
          phase: np.ndarray) -> np.ndarray:
    """(N, 3) linear RGB of camera rays given their hits and which hit points see the sun."""
    hit = np.isfinite(hits.t)
    t = np.where(hit, hits.t, 0.0)
    sun, amb = _light(p)
    alb = ALBEDO[hits.material]
    lam = np.clip(hits.normal @ sun_direction(p), 0.0, None) * lit
    col = alb * (amb + sun * lam)[:, None]
    night = time_of_day(p) == "Night"
    glowing = np.flatnonzero(EMISSIVE[hits.material])  # head/tail light surfaces only
    col[glowing] += EMISSION[hits.material[glowing]] * (1.0 if night else 0.12)
    if night:  # ego headlights: cone around the driving direction, inverse-square fall-off
        cosang = dirs_w @ ego_fwd
        beam = np.clip((cosang - 0.93) / 0.07, 0, 1) * 60.0 / (10.0 + t ** 2)
        col += alb * (beam * np.clip(-np.sum(hits.normal * dirs_w, 1), 0, 1))[:, None]
    cover = road_water_cover(p)
    road = hit & ROAD[hits.material]
    if cover > 0 and road.any():
        d_road, n_road = dirs_w[road], hits.normal[road]
        dot = np.sum(d_road * n_road, 1, keepdims=True)
        refl = d_road - 2 * dot * n_road
        fres = effects.fresnel_reflectance(np.abs(dot[:, 0]))[:, None]
        col[road] = col[road] * (1 - 0.45 * cover) + cover * np.clip(fres * 1.5, 0, 1) * sky_colour(refl, p, phase)
    col[~hit] = sky_colour(dirs_w[~hit], p, phase)
    haze = np.exp(-haze_beta(p) * np.where(hit, t, SKY_HAZE_DISTANCE))[:, None]
    horizon = sky_colour(np.tile([[1.0, 0.0, 0.02]], (1, 1)), p, phase)[0]
    return col * haze + horizon * (1 - haze)


def haze_beta(p: WeatherPreset) -> float:
    """Visible-light extinction (1/m) for distance haze: clear air, fog, rain."""
    return 0.0015 + 3 * fog_extinction(p) + 0.001 * rain_rate_mmh(p) ** 0.6


def _streaks(img: Image.Image, rain: float, night: bool, rng: np.random.Generator) -> Image.Image:
    """Draw rain streaks (count ~ rain rate) onto the full-resolution image."""
    n = int(40 * math.sqrt(rain))
    if n == 0:
        return img
    overlay = Image.new("L", img.size, 0)
    draw = ImageDraw.Draw(overlay)
    w, h = img.size
    x0, y0 = rng.uniform(0, w, n), rng.uniform(0, h, n)
    length = rng.uniform(8, 30, n)
    for x, y, ln in zip(x0, y0, length):
        draw.line([(x, y), (x - 0.25 * ln, y + ln)], fill=int(60 if night else 110), width=1)
    grey = Image.new("RGB", img.size, (200, 205, 215) if not night else (90, 95, 110))
    return Image.composite(grey, img, overlay.point(lambda a: a // 2))


def light_points(vehicles) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World positions (L, 3), facing directions (L, 3) and colours (L, 3) of head/tail lights."""
    pos, face, col = [], [], []
    for v in vehicles:
        l, w, h = v.dims
        fwd = np.array([math.cos(v.heading), math.sin(v.heading), 0.0])
        left = np.array([-fwd[1], fwd[0], 0.0])
        for sign, zf, colour in ((1.0, 0.4, HEADLIGHT_RGB), (-1.0, 0.5, TAILLIGHT_RGB)):
            zf = zf if v.body != "truck" else zf / 2
            for side in (-0.33, 0.33):
                pos.append(np.array([v.x, v.y, 0.0]) + fwd * sign * (l / 2 + 0.02) + left * side * w + [0, 0, zf * h])
                face.append(fwd * sign)
                col.append(colour)
    return np.array(pos).reshape(-1, 3), np.array(face).reshape(-1, 3), np.array(col).reshape(-1, 3)


def add_light_glows(img: np.ndarray, scene: RayScene, lidar2img: np.ndarray, pose, cam_w: np.ndarray,
                    mount_height: float, strength: float, haze_beta: float) -> np.ndarray:
    """Add visible, unoccluded head/tail lights as small Gaussian glows to a uint8 image (H, W, 3), in place.

    The glows are summed in linear [0, 1] floats over the region they cover, then rounded back."""
    pos, face, col = light_points(scene.vehicles)
    if strength <= 0 or len(pos) == 0:
        return img
    to_cam = cam_w - pos
    dist = np.linalg.norm(to_cam, axis=1)
    facing = np.sum(to_cam * face, axis=1) > 0
    dirs = -to_cam / dist[:, None]
    free = scene.cast(cam_w, dirs).t >= dist - 0.3
    local = pose.to_lidar(pos, mount_height)
    uvw = np.c_[local, np.ones(len(local))] @ np.asarray(lidar2img, dtype=np.float64).T
    ok = facing & free & (uvw[:, 2] > 0.5)
    h, w = img.shape[:2]
    patches = []
    for (u, v, z), d, c in zip(uvw[ok, :3], dist[ok], col[ok]):
        u, v = u / z, v / z
        sigma = max(1.0, 2.0 * 721.0 * 0.12 / d)
        r = int(3 * sigma) + 1
        x0, x1, y0, y1 = max(int(u) - r, 0), min(int(u) + r + 1, w), max(int(v) - r, 0), min(int(v) + r + 1, h)
        if x0 < x1 and y0 < y1:
            patches.append((x0, x1, y0, y1, u, v, sigma, strength * math.exp(-haze_beta * d), c))
    if not patches:
        return img
    bx0, by0 = min(p[0] for p in patches), min(p[2] for p in patches)
    bx1, by1 = max(p[1] for p in patches), max(p[3] for p in patches)
    region = img[by0:by1, bx0:bx1].astype(np.float64) / 255.0
    for x0, x1, y0, y1, u, v, sigma, gain, c in patches:
        yy, xx = np.mgrid[y0:y1, x0:x1]
        g = np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma ** 2))
        region[y0 - by0:y1 - by0, x0 - bx0:x1 - bx0] += gain * g[..., None] * c
    img[by0:by1, bx0:bx1] = (np.clip(region, 0, 1) * 255 + 0.5).astype(np.uint8)
    return img


def render(scene: RayScene, lidar2img: np.ndarray, pose, mount_height: float, p: WeatherPreset,
           rng: np.random.Generator, spec: CameraSpec = CameraSpec()) -> np.ndarray:
    """(H, W, 3) uint8 RGB image of the scene (vehicles already set in `scene`)."""
    key = np.ascontiguousarray(lidar2img, dtype=np.float64).tobytes()
    centre, dirs = _rays_cached(key, spec.width, spec.height, spec.downsample)
    h, w = dirs.shape[:2]
    rot = pose.rotation()
    dirs_w = rotate_yaw(dirs.reshape(-1, 3), pose.yaw)
    cam_w = rot @ centre + np.array([pose.x, pose.y, mount_height])
    hits = scene.cast(cam_w, dirs_w)
    phase = rng.uniform(0, 2 * np.pi, 6)
    col = shade(hits, dirs_w, sun_visible(scene, cam_w, dirs_w, hits, p), rot[:, 0], p, phase)
    exposure = (1.0 if time_of_day(p) != "Night" else 2.5) * (1.0 - 0.35 * p.precipitation / 100.0)  # rain darkening
    srgb = np.clip(col * exposure, 0, 1) ** (1 / 2.2)
    small = Image.fromarray((srgb.reshape(h, w, 3) * 255 + 0.5).astype(np.uint8), "RGB")
    img = small.resize((spec.width, spec.height), Image.BILINEAR)
    night = time_of_day(p) == "Night"
    strength = 1.0 if night else (0.4 if p.precipitation > 0 else 0.0)
    if strength > 0:
        glow = add_light_glows(np.array(img), scene, lidar2img, pose, cam_w, mount_height, strength, haze_beta(p))
        img = Image.fromarray(glow, "RGB")
    img = _streaks(img, rain_rate_mmh(p), night, rng)
    return np.asarray(img)
