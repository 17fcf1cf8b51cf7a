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


def test_transmission_power_and_goodin_noise():
    rng = np.random.default_rng(2)
    r = rng.uniform(1, 120, 50)
    t2 = effects.two_way_transmission(r, 0.003, 0.002, 10.0)
    # optical depth as a numerical integral of the extinction along the path, both ways
    depth = np.array([integrate.quad(lambda x: 0.003 + (0.002 if x > 10 else 0.0), 0, ri, points=[10.0])[0] for ri in r])
    np.testing.assert_allclose(t2, np.exp(-2 * depth), rtol=1e-7)
    np.testing.assert_allclose(effects.received_power(0.5, 0.8, r, t2), 0.5 * 0.8 * t2 / r ** 2)
    np.testing.assert_allclose(effects.goodin_range_sigma(r, 4.0), 0.02 * r * (1 - math.exp(-4.0)) ** 2)


def test_inverse_square_sampling_follows_cdf():
    rng = np.random.default_rng(3)
    a, b = 1.0, 12.0
    x = effects.inverse_square_ranges(rng.random(20000), a, np.full(20000, b))
    cdf = lambda r: (1 / a - 1 / np.asarray(r)) / (1 / a - 1 / b)
    assert stats.kstest(x, cdf).pvalue > 0.01


@pytest.mark.parametrize("kind", ["rain", "fog"])
def test_backscatter_rate_matches_formula(kind):
    rng = np.random.default_rng(4)
    n = 200000
    r_hit = rng.uniform(0.5, 60.0, n)
    if kind == "rain":
        alpha = effects.marshall_palmer_extinction(50.0)
        idx, r = effects.rain_backscatter(r_hit, alpha, rng)
        p = 1 - np.exp(-effects.BACKSCATTER_K * alpha * np.clip(np.minimum(r_hit, 12.0) - 1.0, 0, None))
        lo, hi = 1.0, 12.0
    else:
        alpha = 0.03
        idx, r = effects.fog_backscatter(r_hit, alpha, rng)
        beta = 0.046 * alpha / -math.log(0.05)
        p = 1 - np.exp(-effects.FOG_BACKSCATTER_K * beta * np.clip(np.minimum(r_hit, 30.0) - 1.5, 0, None))
        lo, hi = 1.5, 30.0
    assert abs(len(idx) - p.sum()) < 5 * math.sqrt(p.sum()) + 1
    assert (np.diff(idx) > 0).all() and (r <= r_hit[idx] + 1e-9).all() and (r >= lo).all() and (r <= hi).all()
    # ranges follow the 1/r^2 density on [lo, min(r_hit, hi)]: their CDF values are uniform
    far = np.minimum(r_hit[idx], hi)
    assert stats.kstest((1 / lo - 1 / r) / (1 / lo - 1 / far), "uniform").pvalue > 0.01


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
