import math

import numpy as np
import torch

from models import box_coder


def _boxes(rng, n):
    b = rng.random((n, 7)) * [50, 20, 2, 4, 2, 2, 2 * math.pi] + [0, -10, -2, 1, 0.5, 0.5, -math.pi]
    return torch.from_numpy(b.astype(np.float64))


def test_encode_matches_formula_and_roundtrips():
    rng = np.random.default_rng(0)
    g, a = _boxes(rng, 100), _boxes(rng, 100)
    d = box_coder.encode(g, a).numpy()
    gn, an = g.numpy(), a.numpy()
    diag = np.hypot(an[:, 3], an[:, 4])
    np.testing.assert_allclose(d[:, 0], (gn[:, 0] - an[:, 0]) / diag)
    np.testing.assert_allclose(d[:, 2], (gn[:, 2] - an[:, 2]) / an[:, 5])
    np.testing.assert_allclose(d[:, 4], np.log(gn[:, 4] / an[:, 4]))
    np.testing.assert_allclose(d[:, 6], gn[:, 6] - an[:, 6])
    np.testing.assert_allclose(box_coder.decode(box_coder.encode(g, a), a).numpy(), gn, atol=1e-9)


def test_direction_bin_recovers_heading():
    rng = np.random.default_rng(1)
    yaw = torch.from_numpy(rng.random(500) * 2 * math.pi - math.pi)
    bins = box_coder.direction_target(yaw)
    flipped = yaw + math.pi * torch.from_numpy(rng.integers(0, 2, 500).astype(np.float64))  # the network's yaw mod pi
    back = box_coder.apply_direction(flipped, bins).numpy()
    ref = (yaw.numpy() + np.pi) % (2 * np.pi) - np.pi
    diff = (back - ref + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(diff, 0, atol=1e-9)
    assert back.min() >= -np.pi and back.max() < np.pi
