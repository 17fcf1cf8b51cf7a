"""Weather effects on the LiDAR, one published model per function (ranges in metres).

- Rain extinction: Marshall-Palmer drop size distribution N(D) = N0 exp(-Lambda D),
  N0 = 8000 m^-3 mm^-1, Lambda = 4.1 R^-0.21 mm^-1 (R in mm/h), with the geometric-optics
  extinction efficiency Q_ext = 2 that LISA's Mie integral tends to for drops far larger than
  905 nm: alpha = Q_ext * pi/4 * int D^2 N(D) dD = Q_ext * pi * N0 / (2 Lambda^3) [mm^2/m^3].
  Chosen over Goodin's alpha = 0.01 R^0.6 because it follows from the drop physics LISA uses,
  gives ~2.8e-3 1/m at 25 mm/h (in line with measured 905 nm rain extinction) where
  0.01 R^0.6 read in 1/m gives 25x more, and needs no fitted constant.
- Detection threshold from the sensor's spec: received power P = rho cos(theta) T^2 / r^2 of a
  Lambertian target against P_min = min(rho_i / r_i^2) over the spec's detection points (HDL-64E:
  10 % reflectance at 50 m, 80 % at 120 m -> P_min = 4e-5, set by the 10 % point).
- Range noise from the signal (LISA, Kilic et al. 2021): sigma = dR / sqrt(2 SNR), SNR = P / P_min,
  on top of the spec's accuracy floor: sigma = sqrt(sigma0^2 + dR^2 / (2 SNR)).
- Raindrop returns (LISA's Monte Carlo): Marshall-Palmer drops (D >= 0.05 mm) uniform in the beam's
  cone (diameter theta r), each returning P = rho_w T^2(r) min((D / (theta r))^2, 1) / r^2 with
  rho_w = ((n - 1) / (n + 1))^2 of water; the strongest return of the ray (drops and target) wins.
- Wet road: the unpolarised Fresnel reflectance F of water (n = 1.33) sends that share of the
  beam away specularly on the way in and out, and soaked asphalt is darker:
  rho_wet = rho (1 - 0.4 c) ((1 - c) + c (1 - F(theta))^2) for water cover c; spray clouds
  behind moving vehicles.
- Fog (Hahner et al. 2021): Beer-Lambert attenuation alpha = -ln(0.05) / MOR beyond the fog's start;
  soft-target return P_soft(R) = pi beta int sin^2(pi (R - R') / (c tau_H)) xi(R') T^2(R') / R'^2 dR'
  over the pulse's extent R - c tau_H <= R' <= R (sin^2 pulse of half-power width tau_H, crossover
  xi from 0 at 0.9 m to 1 at 1.0 m, beta = 0.046 / MOR), in the same units as P; its peak replaces
  the hard return when stronger (strongest return), at the range gate minus c tau_H / 2.
- Sunlight: false returns with probability p0 sin(sun altitude) (1 - 0.75 cloudiness).
- CARLA's weather-blind sensor: I = exp(-0.004 d), general drop-off 0.45, intensity drop-off
  limit 0.8 and zero-intensity drop-off 0.4.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

MP_N0 = 8000.0  # Marshall-Palmer intercept, m^-3 mm^-1
Q_EXT = 2.0  # extinction efficiency of drops >> wavelength
WATER_INDEX = 1.33
WET_DARKENING = 0.4  # relative albedo loss of a soaked surface
DROP_INDEX = 1.328  # refractive index of water at 905 nm (LISA)
RHO_DROP = ((DROP_INDEX - 1.0) / (DROP_INDEX + 1.0)) ** 2  # Fresnel reflectance of a drop, normal incidence
DROP_MIN_MM = 0.05  # smallest drop LISA samples
FOG_BETA_PER_MOR = 0.046  # Hahner et al.: beta = 0.046 / MOR
FOG_CROSSOVER_M = (0.9, 1.0)  # Hahner et al.: receiver FOV starts / fully covers the beam
LIGHT_SPEED = 299792458.0  # m/s
CARLA_ATTENUATION = 0.004
CARLA_DROPOFF_GENERAL = 0.45
CARLA_DROPOFF_LIMIT = 0.8
CARLA_DROPOFF_ZERO = 0.4


def marshall_palmer_extinction(rain_mmh: float) -> float:
    """Rain extinction coefficient alpha in 1/m for a rain rate in mm/h."""
    if rain_mmh <= 0:
        return 0.0
    lam = 4.1 * rain_mmh ** -0.21  # 1/mm
    return Q_EXT * math.pi * MP_N0 / (2.0 * lam ** 3) * 1e-6


def two_way_transmission(r: np.ndarray, alpha_rain: float, alpha_fog: float = 0.0,
                         fog_start: float = 0.0) -> np.ndarray:
    """Beer-Lambert round-trip transmission T^2 for ranges r (fog only beyond fog_start)."""
    fog_path = np.maximum(r - fog_start, 0.0)
    return np.exp(-2.0 * alpha_rain * r - 2.0 * alpha_fog * fog_path)


def received_power(rho: np.ndarray, cos_inc: np.ndarray, r: np.ndarray, t2: np.ndarray) -> np.ndarray:
    """Relative received power of a Lambertian target: rho cos(theta) T^2 / r^2."""
    return rho * cos_inc * t2 / np.maximum(r, 1e-3) ** 2


def spec_min_power(points: tuple[tuple[float, float], ...]) -> float:
    """P_min of a sensor that detects every (reflectivity, range) point of its spec: min rho / r^2."""
    return min(rho / r ** 2 for rho, r in points)


def lisa_range_sigma(power: np.ndarray, p_min: float, range_accuracy: float, floor: float = 0.0) -> np.ndarray:
    """Range noise sigma (m) of a return of received power P: sqrt(floor^2 + dR^2 / (2 P / P_min)) (LISA)."""
    return np.sqrt(floor ** 2 + range_accuracy ** 2 * p_min / (2.0 * np.asarray(power)))


def fresnel_reflectance(cos_i: np.ndarray, n: float = WATER_INDEX) -> np.ndarray:
    """Unpolarised Fresnel reflectance from air into a medium of index n."""
    cos_i = np.clip(cos_i, 0.0, 1.0)
    sin_t = np.sqrt(1.0 - cos_i ** 2) / n
    cos_t = np.sqrt(np.maximum(1.0 - sin_t ** 2, 0.0))
    rs = (cos_i - n * cos_t) / (cos_i + n * cos_t)
    rp = (cos_t - n * cos_i) / (cos_t + n * cos_i)
    return 0.5 * (rs ** 2 + rp ** 2)


def wet_reflectivity(rho: np.ndarray, cos_i: np.ndarray, cover: float) -> np.ndarray:
    """Diffuse reflectivity of a partly water-covered surface.

    Under the film (share `cover`) the beam crosses the water surface twice, keeping
    (1 - F)^2, and the soaked surface is darker by WET_DARKENING * cover (Lekner & Dorf 1988).
    """
    film = (1.0 - cover) + cover * (1.0 - fresnel_reflectance(cos_i)) ** 2
    return rho * (1.0 - WET_DARKENING * cover) * film


def thinned_bernoulli(n: int, p_max: float, p_of, rng: np.random.Generator) -> np.ndarray:
    """Sorted indices i < n drawn independently with probability p_of(candidates)[i] <= p_max.

    Thinning: candidates are drawn with the constant probability p_max (a binomial count, then
    that many distinct indices), and each is kept with probability p_i / p_max, so only the
    candidates' p_i are evaluated.
    """
    if p_max <= 0 or n == 0:
        return np.zeros(0, np.int64)
    cand = np.sort(rng.choice(n, rng.binomial(n, min(p_max, 1.0)), replace=False))
    return cand[rng.random(len(cand)) * p_max < p_of(cand)]


def first_per_ray(rays: np.ndarray, key: np.ndarray) -> np.ndarray:
    """Positions of the smallest ``key`` of each ray in ``rays`` (ties: the earlier position), sorted by ray."""
    order = np.lexsort((key, rays))
    return order[np.r_[True, rays[order][1:] != rays[order][:-1]]] if len(rays) else order


def mp_slope(rain_mmh: float) -> float:
    """Marshall-Palmer slope Lambda = 4.1 R^-0.21 in 1/mm."""
    return 4.1 * rain_mmh ** -0.21


def drop_power(r: np.ndarray, d_mm: np.ndarray, alpha: float, beam_div: float) -> np.ndarray:
    """LISA's received power of a drop of diameter D at range r: rho_w T^2 min((D / (theta r))^2, 1) / r^2."""
    share = np.minimum((np.asarray(d_mm) * 1e-3 / (beam_div * np.asarray(r))) ** 2, 1.0)
    return RHO_DROP * np.exp(-2.0 * alpha * np.asarray(r)) * share / np.asarray(r) ** 2


def detectable_drop_mm(r: np.ndarray, alpha: float, p_min: float, beam_div: float) -> np.ndarray:
    """Smallest diameter (mm, >= DROP_MIN_MM) of a drop at range r whose drop_power reaches p_min; inf where none."""
    r = np.asarray(r, dtype=np.float64)
    q = p_min * r ** 2 / (RHO_DROP * np.exp(-2.0 * alpha * r))  # share of the beam a drop must cover
    return np.where(q <= 1.0, np.maximum(DROP_MIN_MM, 1e3 * beam_div * r * np.sqrt(np.minimum(q, 1.0))), np.inf)


def rain_drop_returns(path: np.ndarray, rain_mmh: float, alpha: float, p_min: float, r_min: float,
                      beam_div: float, rng: np.random.Generator, n_grid: int = 4096):
    """The strongest detectable raindrop of each ray: (sorted ray indices, ranges, powers).

    LISA's Monte Carlo draws every drop of the beam's cone up to the hard target (`path`, m) and keeps the
    strongest. The same draw restricted to the drops that can be detected (D >= detectable_drop_mm(r)) is
    again a Poisson process, so only those are drawn: per metre of range there are
    N0 exp(-Lambda D_min(r)) / Lambda * pi (theta r)^2 / 4 of them, and given r, D - D_min(r) ~ Exp(Lambda).
    """
    none = np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    if rain_mmh <= 0:
        return none
    lam = mp_slope(rain_mmh)
    r_top = min(float(np.max(path, initial=0.0)), math.sqrt(RHO_DROP / p_min))  # beyond, no drop is detectable
    if r_top <= r_min:
        return none
    grid = np.linspace(r_min, r_top, n_grid)
    d_min = detectable_drop_mm(grid, alpha, p_min, beam_div)
    density = MP_N0 / lam * np.exp(-lam * np.where(np.isfinite(d_min), d_min, 1e9)) * math.pi * (beam_div * grid) ** 2 / 4
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (density[1:] + density[:-1]) * np.diff(grid))])
    mean = np.interp(np.minimum(path, r_top), grid, cum, left=0.0)  # expected detectable drops per ray
    count = rng.poisson(mean)
    rays = np.repeat(np.arange(len(path)), count)
    if len(rays) == 0:
        return none
    r = np.interp(rng.random(len(rays)) * mean[rays], cum, grid)  # inverse CDF of the range
    d = detectable_drop_mm(r, alpha, p_min, beam_div) + rng.exponential(1.0 / lam, len(rays))
    p = drop_power(r, d, alpha, beam_div)
    first = first_per_ray(rays, -p)
    return rays[first], r[first], p[first]


def fog_crossover(r: np.ndarray) -> np.ndarray:
    """Hahner et al.'s linear crossover xi(R): 0 up to 0.9 m, 1 from 1.0 m."""
    r1, r2 = FOG_CROSSOVER_M
    return np.clip((np.asarray(r) - r1) / (r2 - r1), 0.0, 1.0)


def fog_soft_profile(alpha: float, beta: float, fog_start: float, tau_h: float, block: float,
                     step: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Soft-target response P_soft(R) (units of received_power) on a range-gate grid, the fog ending at `block`
    (the hard target): pi beta sum over R' of sin^2(pi (R - R') / (c tau_H)) xi(R') T^2(R') / R'^2 dR'."""
    width = LIGHT_SPEED * tau_h  # range extent of the pulse
    rp = np.arange(step / 2, block, step)  # midpoints of the R' cells
    f = np.where(rp >= fog_start, fog_crossover(rp) * np.exp(-2.0 * alpha * np.maximum(rp - fog_start, 0.0)) / rp ** 2, 0.0)
    kernel = np.sin(np.pi * (np.arange(int(round(width / step))) + 0.5) * step / width) ** 2
    gate = np.arange(1, len(rp) + len(kernel)) * step  # R at the cells' upper edges
    return gate, math.pi * beta * np.convolve(f, kernel)[: len(gate)] * step


@lru_cache(maxsize=16)
def fog_peak_table(alpha: float, beta: float, fog_start: float, tau_h: float, r_max: float,
                   block_step: float = 0.25) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(blocks, peak power, reported range) of the fog's soft return for hard targets at `blocks` (m):
    the peak of fog_soft_profile, reported at its range gate minus c tau_H / 2 (where a hard target's peak lies)."""
    width = LIGHT_SPEED * tau_h
    reach = min(r_max, fog_start + 4 * width + 20.0)  # farther blocks no longer change the peak
    blocks = np.arange(block_step, reach + block_step, block_step)
    peak, at = np.zeros(len(blocks)), np.zeros(len(blocks))
    for j, b in enumerate(blocks):
        gate, p = fog_soft_profile(alpha, beta, fog_start, tau_h, b)
        k = int(np.argmax(p))
        peak[j], at[j] = p[k], gate[k] - width / 2
    return blocks, peak, at


def fog_returns(path: np.ndarray, alpha: float, fog_start: float, tau_h: float, p_min: float, r_max: float):
    """Fog soft returns of the rays whose fog response reaches p_min: (sorted ray indices, ranges, powers)."""
    if alpha <= 0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    beta = FOG_BETA_PER_MOR * alpha / -math.log(0.05)
    blocks, peak, at = fog_peak_table(alpha, beta, fog_start, tau_h, r_max)
    j = np.minimum(np.searchsorted(blocks, path, side="right") - 1, len(blocks) - 1)  # the table's block <= path
    ok = (j >= 0) & (peak[np.maximum(j, 0)] >= p_min)
    idx = np.flatnonzero(ok)
    return idx, at[j[idx]], peak[j[idx]]


def sunlight_probability(sun_altitude_deg: float, cloudiness: float, p0: float = 2e-4) -> float:
    """Per-ray probability of a false return caused by sunlight."""
    sun = max(0.0, math.sin(math.radians(sun_altitude_deg)))
    return p0 * sun * (1.0 - 0.75 * cloudiness / 100.0)


def sunlight_noise(n: int, sun_altitude_deg: float, cloudiness: float, max_range: float,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Sunlight false returns as (sorted ray indices, ranges uniform in [1, max_range])."""
    p = sunlight_probability(sun_altitude_deg, cloudiness)
    idx = thinned_bernoulli(n, p, lambda i: np.full(len(i), p), rng)
    return idx, rng.uniform(1.0, max_range, len(idx))


def spray_cloud(centres: np.ndarray, headings: np.ndarray, dims: np.ndarray, speeds: np.ndarray,
                cover: float, rng: np.random.Generator, density: float = 0.6) -> np.ndarray:
    """(S, 3) spray droplet clusters behind vehicles on a wet road (world frame, metres).

    Count per vehicle ~ Poisson(density * cover * speed[m/s] * width); uniform in a wedge
    up to 4 m long and 1.2 m high behind the rear axle, widening with distance.
    """
    dims = np.asarray(dims, dtype=np.float64).reshape(-1, 3)
    counts = rng.poisson(density * cover * np.maximum(np.asarray(speeds, dtype=np.float64), 0.0) * dims[:, 1])
    k = np.repeat(np.arange(len(counts)), counts)  # vehicle of each cluster
    if len(k) == 0:
        return np.zeros((0, 3))
    length, width = dims[k, 0], dims[k, 1]
    back = rng.uniform(0.0, 4.0, len(k))
    lat = rng.uniform(-0.5, 0.5, len(k)) * (width + 0.3 * back)
    up = rng.uniform(0.05, 0.3 + 0.25 * back)
    fx, fy = np.cos(headings)[k], np.sin(headings)[k]
    x = centres[k, 0] - fx * (length / 2 + back) - fy * lat
    y = centres[k, 1] - fy * (length / 2 + back) + fx * lat
    return np.stack([x, y, centres[k, 2] + up], 1)


def carla_intensity(d: np.ndarray) -> np.ndarray:
    """CARLA's LiDAR intensity: exp(-0.004 d)."""
    return np.exp(-CARLA_ATTENUATION * d)


def carla_keep(intensity: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """CARLA's drop-off: random general drop, then intensity-dependent drop below the limit."""
    general = rng.random(intensity.shape) > CARLA_DROPOFF_GENERAL
    alpha = CARLA_DROPOFF_ZERO / CARLA_DROPOFF_LIMIT
    beta = 1.0 - CARLA_DROPOFF_ZERO
    by_intensity = (intensity > CARLA_DROPOFF_LIMIT) | (rng.random(intensity.shape) < alpha * intensity + beta)
    return general & by_intensity
