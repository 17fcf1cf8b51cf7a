import numpy as np
import torch

from models.losses import box_regression_loss, direction_loss, sigmoid_focal_loss, smooth_l1


def test_focal_loss_matches_numpy():
    rng = np.random.default_rng(0)
    x, t, w = rng.standard_normal(300), rng.integers(0, 2, 300).astype(float), rng.random(300)
    p = 1 / (1 + np.exp(-x))
    pt = np.where(t == 1, p, 1 - p)
    at = np.where(t == 1, 0.25, 0.75)
    ref = (w * at * (1 - pt) ** 2 * -np.log(pt)).sum()
    got = sigmoid_focal_loss(torch.from_numpy(x), torch.from_numpy(t), torch.from_numpy(w))
    np.testing.assert_allclose(float(got), ref, rtol=1e-9)


def test_smooth_l1_and_box_loss_match_numpy():
    rng = np.random.default_rng(1)
    d = rng.standard_normal(200) * 0.3
    beta = 1 / 9
    ref = np.where(np.abs(d) < beta, 0.5 * d ** 2 / beta, np.abs(d) - 0.5 * beta)
    np.testing.assert_allclose(smooth_l1(torch.from_numpy(d)).numpy(), ref, rtol=1e-12)
    p, t = rng.standard_normal((20, 7)), rng.standard_normal((20, 7))
    diff = np.concatenate([p[:, :6] - t[:, :6], np.sin(p[:, 6:] - t[:, 6:])], axis=1)
    r = np.where(np.abs(diff) < beta, 0.5 * diff ** 2 / beta, np.abs(diff) - 0.5 * beta).sum()
    np.testing.assert_allclose(float(box_regression_loss(torch.from_numpy(p), torch.from_numpy(t))), r,
                               rtol=1e-9)


def test_direction_loss_matches_numpy():
    rng = np.random.default_rng(2)
    logits, target = rng.standard_normal((50, 2)), rng.integers(0, 2, 50)
    logp = logits - np.log(np.exp(logits).sum(1, keepdims=True))
    ref = -logp[np.arange(50), target].sum()
    got = direction_loss(torch.from_numpy(logits), torch.from_numpy(target))
    np.testing.assert_allclose(float(got), ref, rtol=1e-9)
