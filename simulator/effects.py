"""Weather effects on the LiDAR, one published model per function (ranges in metres).

- Rain extinction: Marshall-Palmer drop size distribution N(D) = N0 exp(-Lambda D),
  N0 = 8000 m^-3 mm^-1, Lambda = 4.1 R^-0.21 mm^-1 (R in mm/h), with the geometric-optics
  extinction efficiency Q_ext = 2 that LISA's Mie integral tends to for drops far larger than
  905 nm: alpha = Q_ext * pi/4 * int D^2 N(D) dD = Q_ext * pi * N0 / (2 Lambda^3) [mm^2/m^3].
  Chosen over Goodin's alpha = 0.01 R^0.6 because it follows from the drop physics LISA uses,
  gives ~2.8e-3 1/m at 25 mm/h (in line with measured 905 nm rain extinction) where
  0.01 R^0.6 read in 1/m gives 25x more, and needs no fitted constant.
- Power threshold drop-out: P = rho cos(theta) T^2 / r^2 against the sensor's minimum power.
- Range noise in rain (Goodin et al. 2019): sigma = 0.02 r (1 - exp(-R))^2, i.e. ~2 % of the
  range for any rain above ~3 mm/h (LidarSpec.rain_range_noise scales it).
- Raindrop back-scatter (LISA, Kilic et al. 2021): a ray returns from a drop with probability
  1 - exp(-k alpha L) over the first L metres; drop range drawn with density ~ 1/r^2.
- Wet road: the unpolarised Fresnel reflectance F of water (n = 1.33) sends that share of the
  beam away specularly on the way in and out, and soaked asphalt is darker:
  rho_wet = rho (1 - 0.4 c) ((1 - c) + c (1 - F(theta))^2) for water cover c; spray clouds
  behind moving vehicles.
- Fog (Hahner et al. 2021): Beer-Lambert attenuation alpha = -ln(0.05) / MOR; soft-target
  back-scatter with beta = 0.046 / MOR, simplified to a return probability 1 - exp(-k beta L)
  near the sensor that wins when it comes before the hard target (first return).
- Sunlight: false returns with probability p0 sin(sun altitude) (1 - 0.75 cloudiness).
- CARLA's weather-blind sensor: I = exp(-0.004 d), general drop-off 0.45, intensity drop-off
  limit 0.8 and zero-intensity drop-off 0.4.
"""
from __future__ import annotations

import math

import numpy as np

MP_N0 = 8000.0  # Marshall-Palmer intercept, m^-3 mm^-1
Q_EXT = 2.0  # extinction efficiency of drops >> wavelength
WATER_INDEX = 1.33
WET_DARKENING = 0.4  # relative albedo loss of a soaked surface
BACKSCATTER_K = 0.12  # drop returns per unit optical depth: ~0.5 % of rays at 50 mm/h
FOG_BETA_PER_MOR = 0.046  # Hahner et al.: beta = 0.046 / MOR
FOG_BACKSCATTER_K = 8.0  # fog returns per unit back-scatter depth: ~1 % of rays at MOR 1 km
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


def goodin_range_sigma(r: np.ndarray, rain_mmh: float, k: float = 0.02) -> np.ndarray:
    """Standard deviation of the range error in rain (Goodin et al. 2019: k = 0.02), metres."""
    return k * np.asarray(r) * (1.0 - math.exp(-rain_mmh)) ** 2


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


def inverse_square_ranges(u: np.ndarray, r_min: float, r_max: np.ndarray) -> np.ndarray:
    """Inverse CDF of the density ~ 1/r^2 on [r_min, r_max] at uniform samples u."""
    return 1.0 / (1.0 / r_min - u * (1.0 / r_min - 1.0 / r_max))


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


def rain_backscatter(r_hit: np.ndarray, alpha_rain: float, rng: np.random.Generator,
                     r_min: float = 1.0, r_max: float = 12.0) -> tuple[np.ndarray, np.ndarray]:
    """Raindrop returns as (sorted ray indices, ranges).

    Probability 1 - exp(-k alpha L), L = min(r_hit, r_max) - r_min; range density ~ 1/r^2.
    """
    if alpha_rain <= 0:
        return np.zeros(0, np.int64), np.zeros(0)
    p_of = lambda i: 1.0 - np.exp(-BACKSCATTER_K * alpha_rain * np.clip(np.minimum(r_hit[i], r_max) - r_min, 0.0, None))
    idx = thinned_bernoulli(len(r_hit), 1.0 - math.exp(-BACKSCATTER_K * alpha_rain * (r_max - r_min)), p_of, rng)
    return idx, inverse_square_ranges(rng.random(len(idx)), r_min, np.minimum(r_hit[idx], r_max))


def fog_backscatter(r_hit: np.ndarray, alpha_fog: float, rng: np.random.Generator,
                    r_min: float = 1.5, r_max: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """Fog soft-target returns as (sorted ray indices, ranges).

    Back-scatter coefficient beta = 0.046 / MOR with MOR = -ln(0.05) / alpha (Hahner et al.);
    a ray returns from the fog with probability 1 - exp(-k beta L), L the path inside
    [r_min, min(r_hit, r_max)], at a range of density ~ 1/r^2 (the near-range peak of the
    soft-target response).
    """
    if alpha_fog <= 0:
        return np.zeros(0, np.int64), np.zeros(0)
    beta = FOG_BETA_PER_MOR * alpha_fog / -math.log(0.05)
    p_of = lambda i: 1.0 - np.exp(-FOG_BACKSCATTER_K * beta * np.clip(np.minimum(r_hit[i], r_max) - r_min, 0.0, None))
    idx = thinned_bernoulli(len(r_hit), 1.0 - math.exp(-FOG_BACKSCATTER_K * beta * (r_max - r_min)), p_of, rng)
    return idx, inverse_square_ranges(rng.random(len(idx)), r_min, np.minimum(r_hit[idx], r_max))


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
