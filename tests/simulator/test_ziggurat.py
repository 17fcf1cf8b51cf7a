import numpy as np
from scipy import stats

from simulator.ziggurat import ZIG_F, ZIG_V, ZIG_X, normals, standard_normals


def test_layers_have_equal_area():
    x, f = ZIG_X, ZIG_F
    np.testing.assert_allclose(x[1:256] * (f[2:] - f[1:256]), ZIG_V, rtol=1e-8)  # layers 1..255
    assert abs(x[0] * f[1] - ZIG_V) < 1e-15  # the base layer's virtual width
    tail = stats.norm.sf(x[1]) * np.sqrt(2 * np.pi)  # integral of exp(-x^2 / 2) beyond R
    assert abs(x[1] * f[1] + tail - ZIG_V) < 1e-12  # base layer: rectangle up to R plus the tail
    assert x[256] == 0 and (np.diff(x[1:]) < 0).all()


def test_draws_are_standard_normal_and_deterministic():
    z = normals(np.random.default_rng(0), 400_000)
    assert stats.kstest(z, "norm").pvalue > 1e-3
    assert abs(z.mean()) < 0.01 and abs(z.var() - 1) < 0.01
    tail = np.abs(z) > ZIG_X[1]  # the tail branch: P(|z| > R) = 2.6e-4
    assert 40 < tail.sum() < 170 and stats.kstest(np.abs(z[tail]) - ZIG_X[1],
                                                  lambda a: 1 - stats.norm.sf(ZIG_X[1] + a) / stats.norm.sf(ZIG_X[1])
                                                  ).pvalue > 1e-3
    np.testing.assert_array_equal(z, normals(np.random.default_rng(0), 400_000))


def test_running_out_of_words_is_reported_and_retried():
    raw = np.random.default_rng(1).bit_generator.random_raw(1000)
    assert standard_normals(raw, 1000, ZIG_X, ZIG_F)[1] == -1  # ~1.5 % of draws take extra words
    z, used = standard_normals(raw, 900, ZIG_X, ZIG_F)
    assert 900 < used <= 1000 and np.isfinite(z).all()
    np.testing.assert_array_equal(z, standard_normals(raw[:used], 900, ZIG_X, ZIG_F)[0])
    assert len(normals(np.random.default_rng(2), 5)) == 5
