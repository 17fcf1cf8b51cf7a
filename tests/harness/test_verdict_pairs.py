"""Paired comparisons of verdicts: McNemar by hand and against the binomial sum, the bootstrap's unit."""
import math

import numpy as np
import pandas as pd
import pytest

from harness import verdict_pairs


def brute_mcnemar(b, c):
    n = b + c
    if n == 0:
        return 1.0
    k = min(b, c)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n
    return min(1.0, 2 * tail)


def test_mcnemar_by_hand_and_against_the_binomial_sum():
    assert verdict_pairs.mcnemar_p(0, 5) == pytest.approx(2 / 32)  # 0.0625: 5 discordant, all one way, not apart
    assert verdict_pairs.mcnemar_p(0, 6) == pytest.approx(2 / 64)
    assert verdict_pairs.mcnemar_p(0, 0) == 1.0 and verdict_pairs.mcnemar_p(3, 3) == 1.0
    rng = np.random.default_rng(0)
    for b, c in rng.integers(0, 30, (100, 2)):
        assert verdict_pairs.mcnemar_p(int(b), int(c)) == pytest.approx(brute_mcnemar(int(b), int(c)))


def _rows(model, passed, a_req, keys):
    return [{"set": "sweep", "verdict": "perception", "model": model, "instance": k, "preventable": True,
             "body_class": "car", "passed": p, "a_req_mps2": a} for k, p, a in zip(keys, passed, a_req)]


def test_pair_table_by_hand():
    keys = [f"Sweep#{i}" for i in range(8)]
    a_req_a = [1.0, 2.0, 3.0, 4.0, 5.0, 5.5, 2.5, 1.5]
    a_req_b = [1.5, 7.0, 8.0, 9.0, math.inf, math.inf, 3.0, 2.0]
    inst = pd.DataFrame(_rows("a", [x <= 6 for x in a_req_a], a_req_a, keys)
                        + _rows("b", [x <= 6 for x in a_req_b], a_req_b, keys))
    t = verdict_pairs.pair_table(inst, n_boot=200).iloc[0]
    # a passes all 8, b passes 3 (instances 0, 6, 7): 5 discordant one way, p = 0.0625: not apart
    assert (t["a_only"], t["b_only"], t["n_instances"], t["unit"]) == (5, 0, 8, "instances")
    assert t["mcnemar_p"] == pytest.approx(0.0625) and not t["apart"]
    # medians: a (2.5 + 3.0) / 2 = 2.75; b (7 + 8) / 2 = 7.5; b's two never-confirmed can push its median to inf
    assert t["diff_median_a_req"] == pytest.approx(2.75 - 7.5) and t["ci_hi"] < 0.0


def test_pair_table_resamples_drives_of_weather_copies():
    keys = [f"{w}#{i}" for w in ("ClearNoon", "HardRainNoon", "WetNoon") for i in range(3)]
    inst = pd.DataFrame(_rows("a", [True] * 9, [2.0] * 9, keys) + _rows("b", [True] * 9, [2.0] * 9, keys))
    t = verdict_pairs.pair_table(inst, n_boot=50).iloc[0]
    assert (t["unit"], t["n_units"], t["n_instances"]) == ("drives", 3, 9)
    assert t["diff_median_a_req"] == 0.0 and t["ci_lo"] == 0.0 == t["ci_hi"] and t["mcnemar_p"] == 1.0


def test_paired_bootstrap_against_a_loop():
    rng = np.random.default_rng(3)
    a, b = rng.uniform(0, 8, 12), rng.uniform(0, 8, 12)
    units = np.repeat(np.arange(4), 3)
    lo, hi = verdict_pairs.paired_bootstrap_median(a, b, units, 300, seed=7)
    g = np.random.default_rng(7)
    diffs = []
    for _ in range(300):
        pick = g.integers(0, 4, 4)
        idx = np.concatenate([np.flatnonzero(units == k) for k in pick])
        diffs.append(np.median(a[idx]) - np.median(b[idx]))
    ranked = np.sort(diffs)  # the inverted CDF: the ceil(q n)-th smallest
    assert (lo, hi) == pytest.approx((ranked[math.ceil(0.025 * 300) - 1], ranked[math.ceil(0.975 * 300) - 1]))
