"""benchmarks/golden_weights.py: the seeded rules of the golden checkpoints."""
import numpy as np
import pytest

from benchmarks.golden_weights import LARGE, RULES, fill

NAMES = ["conv.weight", "bn.weight", "bn.bias", "bn.running_mean", "bn.running_var", "bn.num_batches_tracked",
         "fc.weight", "dense_head.conv_cls.weight", "dense_head.conv_cls.bias"]
SHAPES = [(16, 4, 3, 3), (16,), (16,), (16,), (16,), (), (64, LARGE // 32), (2, 16, 1, 1), (2,)]


def test_rule_2_is_rule_1_but_above_large_a_float32_uniform_of_the_same_variance():
    one = fill(NAMES, SHAPES, 7, -2.0, 0.5, RULES[0])
    two = fill(NAMES, SHAPES, 7, -2.0, 0.5, RULES[1])
    for name in NAMES[:6]:  # drawn before the large tensor: the same values
        np.testing.assert_array_equal(two[name], one[name])
    fc = two["fc.weight"]  # 2^21 elements, fan_in 2^15
    a = np.sqrt(3 * 2 / 2 ** 15)
    assert fc.dtype == np.float32 and fc.shape == (64, LARGE // 32)
    assert -a <= fc.min() and fc.max() < a and fc.min() < -0.999 * a and fc.max() > 0.999 * a
    assert abs(fc.std() / np.sqrt(2 / 2 ** 15) - 1) < 1e-2 and abs(fc.mean()) < 1e-2 * a
    assert abs(one["fc.weight"].std() / fc.std() - 1) < 1e-2
    assert two["dense_head.conv_cls.bias"].dtype == np.float32
    assert two["bn.num_batches_tracked"].dtype == np.int64


def test_rule_2_without_a_large_tensor_is_rule_1():
    one = fill(NAMES[:6], SHAPES[:6], 3, -1.0, rule=RULES[0])
    two = fill(NAMES[:6], SHAPES[:6], 3, -1.0, rule=RULES[1])
    assert all(np.array_equal(one[n], two[n]) for n in NAMES[:6])


def test_the_rules_repeat_and_an_unknown_rule_is_refused():
    for rule in RULES:
        first, again = fill(NAMES, SHAPES, 5, 0.0, rule=rule), fill(NAMES, SHAPES, 5, 0.0, rule=rule)
        assert all(np.array_equal(first[n], again[n]) for n in NAMES)
    with pytest.raises(ValueError, match="golden-weights-9"):
        fill(NAMES, SHAPES, 5, 0.0, rule="golden-weights-9")
