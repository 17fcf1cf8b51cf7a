import numpy as np
import shapely.geometry as sg
import torch

from models.iou import corners_bev, ioa_bev_sparse, iou_3d, iou_bev, iou_bev_pairs, iou_bev_sparse


def _boxes(rng, n, spread=6.0):
    b = np.zeros((n, 7), np.float32)
    b[:, :2] = rng.random((n, 2)) * spread
    b[:, 2] = rng.random(n)
    b[:, 3:6] = rng.random((n, 3)) * [4, 2, 1.5] + [0.5, 0.3, 0.5]
    b[:, 6] = rng.random(n) * 2 * np.pi - np.pi
    return b


def _poly(box):
    return sg.Polygon(corners_bev(torch.from_numpy(box)).numpy())


def _shapely_iou(a, b, three_d=False):
    out = np.zeros((len(a), len(b)))
    for i, x in enumerate(a):
        for j, y in enumerate(b):
            inter = _poly(x).intersection(_poly(y)).area
            va, vb = x[3] * x[4], y[3] * y[4]
            if three_d:
                dz = max(0.0, min(x[2] + x[5] / 2, y[2] + y[5] / 2) - max(x[2] - x[5] / 2, y[2] - y[5] / 2))
                inter, va, vb = inter * dz, va * x[5], vb * y[5]
            out[i, j] = inter / (va + vb - inter)
    return out


def test_iou_bev_and_3d_match_shapely():
    rng = np.random.default_rng(0)
    a, b = _boxes(rng, 25), _boxes(rng, 30)
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    np.testing.assert_allclose(iou_bev(ta, tb).numpy(), _shapely_iou(a, b), atol=2e-5)
    np.testing.assert_allclose(iou_3d(ta, tb).numpy(), _shapely_iou(a, b, True), atol=2e-5)
    np.testing.assert_allclose(iou_bev_sparse(ta, tb).numpy(), _shapely_iou(a, b), atol=2e-5)


def test_ioa_bev_sparse_matches_shapely():
    rng = np.random.default_rng(3)
    a, b = _boxes(rng, 25), _boxes(rng, 30)
    want = np.array([[_poly(x).intersection(_poly(y)).area / (x[3] * x[4]) for y in b] for x in a])
    np.testing.assert_allclose(ioa_bev_sparse(torch.from_numpy(a), torch.from_numpy(b)).numpy(), want, atol=2e-5)
    # a car-sized box on a truck: all of it inside (IoU 8.55 / 29.3 = 0.29)
    car, truck = torch.tensor([[2.25, 0, 0, 4.5, 1.9, 1.5, 0]]), torch.tensor([[5.75, 0, 0, 11.5, 2.55, 3.8, 0]])
    assert abs(float(ioa_bev_sparse(car, truck)) - 1.0) < 1e-6 and float(iou_bev_sparse(car, truck)) < 0.3


def test_iou_degenerate_cases():
    rng = np.random.default_rng(1)
    a = torch.from_numpy(_boxes(rng, 20))
    np.testing.assert_allclose(iou_bev_pairs(a, a).numpy(), 1.0, atol=1e-5)  # identical boxes
    turned = a.clone()
    turned[:, 6] += np.pi  # same rectangle, opposite heading
    np.testing.assert_allclose(iou_bev_pairs(a, turned).numpy(), 1.0, atol=1e-5)
    far = a.clone()
    far[:, 0] += 100
    assert float(iou_bev_pairs(a, far).abs().max()) == 0.0
    inner = a.clone()
    inner[:, 3:5] *= 0.5  # nested rectangle: IoU = 1/4
    np.testing.assert_allclose(iou_bev_pairs(a, inner).numpy(), 0.25, atol=1e-5)
    assert iou_bev(a[:0], a).shape == (0, 20)


def test_iou_bev_sparse_equals_every_pair_bit_for_bit():
    """The pruned, chunked anchor x box IoU against iou_bev_pairs of every pair: equal bits, with
    anchors on a grid 70 m out, boxes of any heading among them, touching and nearly touching."""
    from models import iou as iou_mod
    rng = np.random.default_rng(5)
    xs, ys = np.meshgrid(np.arange(60.0, 80.0, 0.4), np.arange(-8.0, 8.0, 0.4))
    n = xs.size
    anchors = np.c_[xs.ravel(), ys.ravel(), np.full(n, -1.0), np.full(n, 3.9), np.full(n, 1.6), np.full(n, 1.56),
                    rng.choice([0.0, np.pi / 2], n)]
    k = 12
    boxes = np.c_[rng.uniform(60, 80, k), rng.uniform(-8, 8, k), np.full(k, -1.0), rng.uniform(0.5, 5, k),
                  rng.uniform(0.3, 2, k), np.full(k, 1.5), rng.uniform(-np.pi, np.pi, k)]
    boxes[0] = anchors[100] + [3.9 + 0.1 + 1e-4, 0, 0, 0, 0, 0, 0]  # just beyond the gap along x
    boxes[1] = anchors[100] + [3.9, 0, 0, 0, 0, 0, 0]  # touching
    boxes[1, 6] = boxes[0, 6] = anchors[100, 6] = 0.0
    ta, tb = torch.tensor(anchors, dtype=torch.float32), torch.tensor(boxes, dtype=torch.float32)
    ia, ib = torch.meshgrid(torch.arange(n), torch.arange(k), indexing="ij")
    every = iou_bev_pairs(ta[ia.reshape(-1)], tb[ib.reshape(-1)]).reshape(n, k)
    assert torch.equal(iou_bev_sparse(ta, tb), every)
    apart = iou_mod.bounds_apart(ta[ia.reshape(-1)], tb[ib.reshape(-1)], gap=0.0).reshape(n, k)
    assert (every[apart] == 0).all() and (every > 0).sum() > 50
