import math

import numpy as np
import pytest
from scipy import integrate, stats

from simulator import effects


def test_marshall_palmer_matches_dsd_integral():
    rng = np.random.default_rng(0)
    for rate in rng.uniform(0.5, 80.0, 5):
        lam = 4.1 * rate ** -0.21
        integral, _ = integrate.quad(lambda d: math.pi / 4 * d ** 2 * 8000.0 * math.exp(-lam * d), 0, 50)
        assert effects.marshall_palmer_extinction(rate) == pytest.approx(2.0 * integral * 1e-6, rel=1e-6)
    assert effects.marshall_palmer_extinction(0.0) == 0.0


def test_fresnel_matches_snell_form():
    rng = np.random.default_rng(1)
    ti = rng.uniform(0.01, 1.55, 200)
    tt = np.arcsin(np.sin(ti) / 1.33)
    ref = 0.5 * (np.sin(ti - tt) ** 2 / np.sin(ti + tt) ** 2 + np.tan(ti - tt) ** 2 / np.tan(ti + tt) ** 2)
    np.testing.assert_allclose(effects.fresnel_reflectance(np.cos(ti)), ref, rtol=1e-9)
    cover = 0.7
    np.testing.assert_allclose(effects.wet_reflectivity(np.full(200, 0.2), np.cos(ti), cover),
                               0.2 * (1 - 0.4 * cover) * ((1 - cover) + cover * (1 - ref) ** 2))


def test_transmission_and_power():
    rng = np.random.default_rng(2)
    r = rng.uniform(1, 120, 50)
    t2 = effects.two_way_transmission(r, 0.003, 0.002, 10.0)
    # optical depth as a numerical integral of the extinction along the path, both ways
    depth = np.array([integrate.quad(lambda x: 0.003 + (0.002 if x > 10 else 0.0), 0, ri, points=[10.0])[0] for ri in r])
    np.testing.assert_allclose(t2, np.exp(-2 * depth), rtol=1e-7)
    np.testing.assert_allclose(effects.received_power(0.5, 0.8, r, t2), 0.5 * 0.8 * t2 / r ** 2)


def test_detection_threshold_from_the_hdl64e_spec():
    """HDL-64E: 10 % reflectance detected at 50 m, 80 % at 120 m (Lambertian, normal incidence)."""
    from simulator.lidar import LidarSpec, detection_range
    from simulator.weather import WEATHER_PRESETS

    spec = LidarSpec()
    p_min = spec.min_power
    assert p_min == pytest.approx(min(0.10 / 50.0 ** 2, 0.80 / 120.0 ** 2))
    assert 0.10 / 50.0 ** 2 >= p_min and 0.80 / 120.0 ** 2 >= p_min  # both spec points detected
    assert 0.10 / 50.5 ** 2 < p_min  # and no margin beyond the weaker one
    assert p_min / (0.02 / 120.0 ** 2) == pytest.approx(28.8)  # the former threshold was 29x more sensitive
    assert detection_range(spec, WEATHER_PRESETS["ClearNoon"], 0.10) == pytest.approx(50.0, abs=0.01)
    assert detection_range(spec, WEATHER_PRESETS["ClearNoon"], 0.80) == pytest.approx(120.0)


def _mp_alpha(rate):
    lam = 4.1 * rate ** -0.21
    return 2.0 * integrate.quad(lambda d: math.pi / 4 * d ** 2 * 8000.0 * math.exp(-lam * d), 0, 50)[0] * 1e-6


def test_rain_range_noise_follows_lisa_and_stays_small():
    """sigma = dR / sqrt(2 SNR) (LISA) over the spec's floor; a detected return has SNR >= 1."""
    rng = np.random.default_rng(3)
    p_min, dr, floor = 4e-5, 0.04, 0.02
    power = p_min * rng.uniform(1, 1e4, 200)
    np.testing.assert_allclose(effects.lisa_range_sigma(power, p_min, dr, floor),
                               np.sqrt(floor ** 2 + (dr / np.sqrt(2 * power / p_min)) ** 2), rtol=1e-12)
    # a 10 % target in 50 mm/h rain: at 50 m it drops out (T^2 ~ 0.65), nearer it is seen with sigma < 0.2 m
    t2 = lambda r: math.exp(-2 * _mp_alpha(50.0) * r)
    assert 0.10 * t2(50.0) / 50.0 ** 2 < p_min and 0.6 < t2(50.0) < 0.7
    for r in (10.0, 30.0, 45.0):
        p = 0.10 * t2(r) / r ** 2
        if p >= p_min:
            assert effects.lisa_range_sigma(p, p_min, dr, floor) < 0.2
    assert effects.lisa_range_sigma(p_min, p_min, dr, floor) < 0.2  # the worst detected return


def _lisa_brute_force(path, rate, alpha, p_min, r_min, theta, rng):
    """LISA's per-ray Monte Carlo written from its equations: every drop (D >= 0.05 mm) of the beam's cone."""
    lam = 4.1 * rate ** -0.21
    n_tot = 8000.0 * math.exp(-lam * 0.05) / lam  # drops per m^3
    volume = math.pi / 3 * path * (theta * path / 2) ** 2  # the cone up to the target
    count = rng.poisson(n_tot * volume)
    ray = np.repeat(np.arange(len(path)), count)
    r = path[ray] * rng.random(len(ray)) ** (1 / 3)  # uniform in the cone: density ~ r^2
    d = 0.05 + rng.exponential(1 / lam, len(ray))
    rho_w = ((1.328 - 1) / (1.328 + 1)) ** 2
    p = np.where(r > r_min, rho_w * np.exp(-2 * alpha * r) * np.minimum((d * 1e-3 / (theta * r)) ** 2, 1) / r ** 2, 0)
    best = np.zeros(len(path))
    np.maximum.at(best, ray, p)
    at = np.zeros(len(path))
    hit = p >= best[ray]
    at[ray[hit]] = r[hit]
    seen = best >= p_min
    return np.flatnonzero(seen), at[seen], best[seen]


@pytest.mark.parametrize("rate", [4.5, 50.0])
def test_raindrop_returns_match_lisa_monte_carlo(rate):
    rng = np.random.default_rng(4)
    n = 6000
    path = rng.choice([2.5, 6.0, 40.0], n)
    alpha, p_min, theta = effects.marshall_palmer_extinction(rate), 4e-5, 3e-3
    idx, r, p = effects.rain_drop_returns(path, rate, alpha, p_min, 1.0, theta, rng)
    ref_idx, ref_r, ref_p = _lisa_brute_force(path, rate, alpha, p_min, 1.0, theta, rng)
    assert (np.diff(idx) > 0).all() and (p >= p_min).all() and (r >= 1.0).all() and (r <= path[idx]).all()
    for short in (2.5, 6.0, 40.0):  # the share of rays a drop takes, per path length
        k, k_ref = (path[idx] == short).sum(), (path[ref_idx] == short).sum()
        assert abs(k - k_ref) < 5 * math.sqrt(k_ref + 1) + 2, (short, k, k_ref)
    assert len(ref_idx) > 50
    assert stats.ks_2samp(r, ref_r).pvalue > 0.001 and stats.ks_2samp(np.log(p), np.log(ref_p)).pvalue > 0.001
    if rate == 50.0:  # graded with the rain rate
        few = effects.rain_drop_returns(path, 4.5, effects.marshall_palmer_extinction(4.5), p_min, 1.0, theta, rng)[0]
        assert len(few) < 0.6 * len(idx)


def _hahner_soft(gate, alpha, beta, fog_start, tau_h, block):
    """Hahner et al. 2021's soft-target response P_soft(R) = C_A P0 beta int_0^{2 tau_H} sin^2(pi t / (2 tau_H))
    xi(R') exp(-2 alpha R') / R'^2 dt, R' = R - c t / 2, normalised as rho cos T^2 / r^2 is (a Lambertian hard
    target's beta_0 = rho / pi, and the delta function's 2 / c kept: a factor pi c / 2)."""
    c = 299792458.0

    def integrand(t):
        rp = gate - c * t / 2
        if rp < fog_start or rp >= block or rp <= 0.9:
            return 0.0
        xi = min((rp - 0.9) / 0.1, 1.0)
        return math.sin(math.pi * t / (2 * tau_h)) ** 2 * xi * math.exp(-2 * alpha * (rp - fog_start)) / rp ** 2

    t_edges = sorted({0.0, 2 * tau_h, *[min(max(2 * (gate - x) / c, 0), 2 * tau_h) for x in (fog_start, block, 0.9, 1.0)]})
    total = sum(integrate.quad(integrand, a, b, limit=200)[0] for a, b in zip(t_edges, t_edges[1:]) if b > a)
    return math.pi * beta * total * c / 2


def test_fog_soft_target_matches_hahner_integral():
    mor, fog_start, tau_h = 60.0, 0.0, 20e-9
    alpha = -math.log(0.05) / mor
    beta = 0.046 / mor
    for block in (3.0, 120.0):
        gate, prof = effects.fog_soft_profile(alpha, beta, fog_start, tau_h, block)
        for g in (1.5, 3.0, 5.0, 8.0):
            k = int(np.argmin(np.abs(gate - g)))
            assert prof[k] == pytest.approx(_hahner_soft(gate[k], alpha, beta, fog_start, tau_h, block), rel=2e-3)
    # the fog's return: the profile's peak, at its range gate minus c tau_H / 2; a fog starting later is weaker
    idx, r, p = effects.fog_returns(np.array([120.0, 2.0]), alpha, fog_start, tau_h, 4e-5, 120.0)
    gates = np.linspace(1.0, 12.0, 221)
    ref = [_hahner_soft(g, alpha, beta, fog_start, tau_h, 120.0) for g in gates]
    assert p[0] == pytest.approx(max(ref), rel=5e-3)
    assert r[0] == pytest.approx(gates[int(np.argmax(ref))] - 299792458.0 * tau_h / 2, abs=0.06)
    assert len(idx) == 2 and p[1] < p[0]  # a target at 2 m cuts the fog short
    later = effects.fog_returns(np.array([120.0]), alpha, 20.0, tau_h, 4e-5, 120.0)
    assert len(later[0]) == 0 or later[2][0] < 0.2 * p[0]
    assert len(effects.fog_returns(np.array([120.0]), 0.0, 0.0, tau_h, 4e-5, 120.0)[0]) == 0


def test_carla_dropoff_and_intensity():
    rng = np.random.default_rng(5)
    d = rng.uniform(0, 200, 300000)
    inten = effects.carla_intensity(d)
    np.testing.assert_allclose(inten, np.exp(-0.004 * d))
    keep = effects.carla_keep(inten, rng)
    p_int = np.where(inten > 0.8, 1.0, (0.4 / 0.8) * inten + 0.6)
    expected = 0.55 * p_int
    assert abs(keep.sum() - expected.sum()) < 5 * math.sqrt(expected.sum())


def test_sunlight_probability_scales_with_altitude():
    assert effects.sunlight_probability(-90, 0) == 0
    assert effects.sunlight_probability(90, 0) == pytest.approx(2e-4)
    assert effects.sunlight_probability(30, 100) == pytest.approx(2e-4 * 0.5 * 0.25)
    rng = np.random.default_rng(6)
    idx, r = effects.sunlight_noise(500000, 90, 0, 120, rng)
    assert abs(len(idx) - 100) < 5 * 10 and (r >= 1).all() and (r <= 120).all()


def test_spray_behind_vehicle():
    rng = np.random.default_rng(7)
    pts = effects.spray_cloud(np.array([[10.0, 5.0, 0.0]]), np.array([0.0]), np.array([[4.0, 2.0, 1.5]]),
                              np.array([30.0]), 1.0, rng)
    assert len(pts) > 0 and (pts[:, 0] <= 10.0 - 2.0).all() and (pts[:, 2] >= 0).all()
    assert len(effects.spray_cloud(np.array([[0.0, 0, 0]]), np.array([0.0]), np.array([[4.0, 2, 1.5]]),
                                   np.array([30.0]), 0.0, rng)) == 0


def test_thinned_bernoulli_hits_each_index_with_its_probability():
    rng = np.random.default_rng(8)
    n, trials = 40, 20000
    p = rng.uniform(0.0, 0.05, n)
    p[:3] = [0.0, 0.05, 0.025]
    calls = []
    counts = np.zeros(n)
    for _ in range(trials):
        idx = effects.thinned_bernoulli(n, 0.05, lambda i: (calls.append(len(i)), p[i])[1], rng)
        assert (np.diff(idx) > 0).all()
        counts[idx] += 1
    expected = trials * p
    assert counts[0] == 0
    np.testing.assert_array_less(np.abs(counts - expected), 5 * np.sqrt(expected * (1 - p)) + 1)
    assert abs(np.mean(calls) - n * 0.05) < 0.1  # only the candidates' probabilities are evaluated
    assert len(effects.thinned_bernoulli(n, 0.0, lambda i: p[i], rng)) == 0


def test_spray_counts_and_wedges_per_vehicle():
    rng = np.random.default_rng(9)
    centres = np.array([[0.0, 0.0, 0.0], [50.0, 10.0, 0.0], [-30.0, 4.0, 0.0]])
    headings, dims = np.array([0.3, -2.0, 3.0]), np.array([[4.5, 1.8, 1.5], [11.0, 2.5, 3.8], [4.0, 1.7, 1.4]])
    speeds, cover = np.array([30.0, 20.0, 0.0]), 0.8
    counts, trials = np.zeros(3), 300
    for _ in range(trials):
        pts = effects.spray_cloud(centres, headings, dims, speeds, cover, rng)
        k = np.linalg.norm(pts[:, None, :2] - centres[None, :, :2], axis=2).argmin(1)  # vehicles far apart
        rel = pts[:, :2] - centres[k, :2]
        fwd = rel[:, 0] * np.cos(headings[k]) + rel[:, 1] * np.sin(headings[k])
        lat = -rel[:, 0] * np.sin(headings[k]) + rel[:, 1] * np.cos(headings[k])
        back = -fwd - dims[k, 0] / 2
        assert (back >= 0).all() and (back <= 4).all() and (np.abs(lat) <= 0.5 * (dims[k, 1] + 0.3 * back)).all()
        assert (pts[:, 2] >= 0.05).all() and (pts[:, 2] <= 0.3 + 0.25 * back).all()
        counts += np.bincount(k, minlength=3)
    mean = 0.6 * cover * speeds * dims[:, 1]
    np.testing.assert_array_less(np.abs(counts / trials - mean), 5 * np.sqrt(mean / trials) + 1e-9)


def test_first_per_ray_matches_a_loop():
    rng = np.random.default_rng(10)
    rays = rng.integers(0, 40, 300)
    key = rng.choice([1.0, 2.0, 3.0], 300)  # many ties: the earlier position wins
    best = {}
    for pos, (ray, k) in enumerate(zip(rays, key)):
        if ray not in best or k < key[best[ray]]:
            best[ray] = pos
    np.testing.assert_array_equal(effects.first_per_ray(rays, key), [best[r] for r in sorted(best)])
    assert len(effects.first_per_ray(np.zeros(0, np.int64), np.zeros(0))) == 0
