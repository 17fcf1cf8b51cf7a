import pytest

from harness.core.braking import stopping_distance


def test_stopping_distance_by_hand():
    assert stopping_distance(10.0) == pytest.approx(10.0 * 1.0 + 100.0 / 8.0 + 2.0)
    assert stopping_distance(-3.0) == pytest.approx(2.0)  # not closing in: margin only
    assert stopping_distance(0.0, margin=0.0) == 0.0
