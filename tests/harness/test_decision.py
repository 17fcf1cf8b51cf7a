"""Confirmation in a window of seconds, processed frames at a latency, a_req and margin: by hand and brute force."""
import math

import numpy as np
import pytest

from harness import decision

T10 = np.round(np.arange(30) * 0.1, 3)  # 10 Hz


def brute_confirm(t, hits, k, window):
    for i in range(len(t)):
        n = sum(1 for j in range(i + 1) if hits[j] and t[j] > t[i] - window + 1e-6)
        if hits[i] and n >= k:
            return i
    return None


def brute_processed(t, latency):
    keep, busy_until = [], -1e9
    for ti in t:
        take = ti >= busy_until - 1e-6
        keep.append(take)
        if take:
            busy_until = ti + latency
    return keep


def test_confirm_index_by_hand():
    hits = np.zeros(30, bool)
    hits[[2, 5, 6]] = True  # frames 2..6 span 0.4 s: inside (0.1, 0.6]
    assert decision.confirm_index(T10, hits) == 6
    hits = np.zeros(30, bool)
    hits[[2, 6, 7]] = True  # frame 2 (0.2 s) is not within 0.5 s of frame 7 (0.7 s): the window is (0.2, 0.7]
    assert decision.confirm_index(T10, hits) is None
    assert decision.confirm_index(T10, np.ones(30, bool)) == 2
    assert decision.confirm_index([], []) is None
    with pytest.raises(ValueError, match="k >= 1"):
        decision.confirm_index(T10, np.ones(30, bool), k=0)


def test_confirm_index_against_brute_force():
    rng = np.random.default_rng(0)
    for _ in range(300):
        n = int(rng.integers(0, 40))
        t = np.round(np.cumsum(rng.choice([0.1, 0.1, 0.2, 0.5], n)), 3)
        hits = rng.uniform(size=n) < rng.uniform()
        k, window = int(rng.integers(1, 5)), float(rng.choice([0.3, 0.5, 1.0]))
        assert decision.confirm_index(t, hits, k, window) == brute_confirm(t, hits, k, window)


def test_confirm_window_stretches_to_k_frames():
    assert decision.confirm_window(0.5, 3, 0.1) == 0.5  # 3 of the 5 frames at 10 Hz
    assert decision.confirm_window(0.5, 3, 0.3) == pytest.approx(0.9)  # every 3rd frame: 3 of 3 processed
    assert decision.confirm_window(0.5, 3, 0.5) == pytest.approx(1.5)  # a 2 Hz set
    assert decision.confirm_window(0.5, 3, float("nan")) == 0.5
    t = np.round(np.arange(10) * 0.3, 3)  # 3 consecutive frames 0.3 s apart confirm in the stretched window
    assert decision.confirm_index(t, np.ones(10, bool), 3, decision.confirm_window(0.5, 3, 0.3)) == 2


def test_processed_frames_by_hand_and_brute_force():
    assert decision.processed_frames(T10[:7], 0.0).all()
    assert decision.processed_frames(T10[:7], 0.1).all()  # free again exactly when the next frame arrives
    assert np.flatnonzero(decision.processed_frames(T10[:10], 0.242)).tolist() == [0, 3, 6, 9]
    assert np.flatnonzero(decision.processed_frames(T10[:10], 0.155)).tolist() == [0, 2, 4, 6, 8]
    with pytest.raises(ValueError, match=">= 0"):
        decision.processed_frames(T10, -0.01)
    rng = np.random.default_rng(1)
    for _ in range(200):
        t = np.round(np.cumsum(rng.choice([0.1, 0.2], int(rng.integers(0, 30)))), 3)
        lat = float(rng.uniform(0, 0.6))
        assert decision.processed_frames(t, lat).tolist() == brute_processed(t, lat)


def test_a_req_and_margin_by_hand():
    # 40 m gap closing at 10 m/s: 100 / (2 * 38) = 1.316 m/s^2; at 6 m/s^2 it needs 8.33 m + 2 m: 29.67 m to spare
    assert decision.a_required(40.0, 10.0) == pytest.approx(100 / 76)
    assert decision.margin_m(40.0, 10.0) == pytest.approx(40 - 2 - 100 / 12)
    assert decision.a_required(2.0, 10.0) == math.inf and decision.a_required(1.0, -3.0) == 0.0
    assert decision.margin_m(10.0, -3.0) == 8.0
    # the study's instance: 68.15 m, 8.33 m/s; a decision 6 s later leaves 18.17 m: 69.4 / (2 * 16.17) = 2.15 m/s^2
    out = decision.outcome(68.15, 25 / 3, 6.0)
    assert out["gap_m"] == pytest.approx(68.15 - 50.0) and out["a_req_mps2"] == pytest.approx((25 / 3) ** 2 / 32.3)
    assert decision.passes(6.0) and not decision.passes(6.01) and decision.passes(3.9, 4.0)


def test_a_req_and_margin_against_numbers():
    rng = np.random.default_rng(2)
    gap, dv = rng.uniform(-5, 120, 500), rng.uniform(-5, 30, 500)
    for g, v in zip(gap, dv):
        a = decision.a_required(g, v)
        m = decision.margin_m(g, v)
        if v > 0 and g > 2:
            # braking at a_req from the gap ends exactly 2 m short: v^2 = 2 a (g - 2)
            assert v * v == pytest.approx(2 * a * (g - 2))
            assert (m >= 0) == (a <= 6.0 + 1e-12) or abs(m) < 1e-9
        elif v > 0:
            assert a == math.inf and m < 0
        else:
            assert a == 0.0 and m == pytest.approx(g - 2)


def test_unpreventable_reason():
    assert decision.unpreventable_reason(False, True, True) == "kinematics"
    assert decision.unpreventable_reason(True, True, False) == "occlusion"
    assert decision.unpreventable_reason(True, False, True) == "range"
    assert decision.unpreventable_reason(True, False, False) == "occlusion and range"
    assert decision.unpreventable_reason(True, True, True) == "occlusion and range"
