"""benchmarks/ort_vs_openvino.py: the paired ratio and its bootstrap interval."""
import numpy as np

from benchmarks.ort_vs_openvino import paired_ratio


def test_paired_ratio_is_the_median_of_per_frame_ratios():
    rng = np.random.default_rng(0)
    first = rng.uniform(50, 150, 41)
    second = first * rng.uniform(0.85, 0.95, 41)  # every frame faster in the second runtime
    med, lo, hi = paired_ratio(first, second)
    assert med == np.median(second / first)
    assert 0.85 <= lo <= med <= hi < 0.95
    # the machine's drift is common to both runtimes: a frame twice as slow in both changes nothing
    drift = np.linspace(1, 2, 41)
    assert paired_ratio(first * drift, second * drift)[0] == med


def test_identical_times_give_a_ratio_of_one():
    t = np.array([10.0, 20.0, 30.0])
    assert paired_ratio(t, t) == (1.0, 1.0, 1.0)
