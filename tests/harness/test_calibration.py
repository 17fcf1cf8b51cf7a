import numpy as np
import pytest

from harness import calibration
from tests.harness.test_sotif_space import make_instances


def reference_ece(scores, correct, n_bins=10):
    """Independent reference: loop over bins [i/n, (i+1)/n), the last closed at 1."""
    total, ece = len(scores), 0.0
    acc, conf = [], []
    for i in range(n_bins):
        lo, hi = i / n_bins, (i + 1) / n_bins
        inside = [(s, c) for s, c in zip(scores, correct) if lo <= s < hi or (i == n_bins - 1 and s == 1.0)]
        if not inside:
            acc.append(None)
            conf.append(None)
            continue
        a = sum(c for _, c in inside) / len(inside)
        m = sum(s for s, _ in inside) / len(inside)
        acc.append(a)
        conf.append(m)
        ece += len(inside) / total * abs(a - m)
    return ece, acc, conf


def test_reliability_against_a_loop():
    rng = np.random.default_rng(0)
    for _ in range(50):
        n = int(rng.integers(1, 300))
        scores = np.r_[rng.uniform(0, 1, n - 1), rng.choice([0.0, 0.5, 1.0])]  # bin edges included
        correct = rng.uniform(size=n) < scores  # roughly calibrated
        got = calibration.reliability(scores, correct)
        ece, acc, conf = reference_ece(scores.tolist(), correct.tolist())
        assert got["ece"] == pytest.approx(ece, abs=1e-12) and got["n"] == n
        assert got["bins"]["accuracy"] == pytest.approx(acc) and got["bins"]["confidence"] == pytest.approx(conf)
    assert calibration.reliability([], [])["ece"] is None


def test_always_right_at_score_one_is_calibrated():
    assert calibration.reliability([1.0, 1.0], [True, True])["ece"] == 0.0
    assert calibration.reliability([0.95, 0.95], [False, False])["ece"] == pytest.approx(0.95)


def test_match_3d_takes_each_ground_truth_once():
    gt = np.array([[10, 0, 0, 4, 2, 1.5, 0]], float)
    boxes = np.array([[10.0, 0, 0, 4, 2, 1.5, 0], [10.3, 0, 0, 4, 2, 1.5, 0], [10, 0, 1.0, 4, 2, 1.5, 0]], float)
    assert calibration.match_3d(boxes, np.array([0.5, 0.9, 0.1]), gt, 0.7).tolist() == [False, True, False]
    # the 1 m higher box shares 0.5 m of a 2.5 m high union: 3D IoU 0.2, matched at neither 0.7 nor 0.5
    assert calibration.match_3d(boxes[2:], np.array([0.9]), gt, 0.5).tolist() == [False]
    assert calibration.match_3d(boxes[:0], np.zeros(0), gt, 0.5).shape == (0,)


def test_calibration_view_per_weather_class(tmp_path):
    root, pred = make_instances(tmp_path / "d", {("ClearNoon", 0): (25.0, 15.0, [1, 0] * 5)})
    view = calibration.calibration_view(root, pred)
    assert set(view) == {"0.7", "0.5"} and set(view["0.7"]) == {"all", "dry"}
    r = view["0.7"]["all"]
    # 12 boxes of score 0.9: the 2 before the lane change and 5 after it on the car, 5 shifted away
    assert r["n"] == 12 and r["bins"]["count"][9] == 12
    assert r["bins"]["accuracy"][9] == pytest.approx(7 / 12) and r["ece"] == pytest.approx(abs(7 / 12 - 0.9))
