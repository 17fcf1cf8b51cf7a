import numpy as np
import torch

from models.box_frame import inside_boxes, inside_local, rotate_to_box_frame, to_box_frame


def _boxes(rng, k):
    centre = rng.uniform(-10, 10, (k, 3))
    size = rng.uniform(0.5, 5.0, (k, 3))
    yaw = rng.uniform(-np.pi, np.pi, (k, 1))
    return np.concatenate([centre, size, yaw], 1).astype(np.float32)


def _numpy_frame(xyz, boxes):
    """(K, N, 3) points relative to each centre, rotated by -yaw (float64)."""
    d = xyz[None].astype(np.float64) - boxes[:, None, :3]
    c, s = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    return np.stack([d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c, d[..., 2]], -1)


def test_box_frame_matches_numpy_and_the_rotation_of_offsets():
    rng = np.random.default_rng(0)
    for n, k in ((0, 3), (200, 0), (500, 7)):
        xyz, boxes = rng.uniform(-12, 12, (n, 3)).astype(np.float32), _boxes(rng, k)
        got = to_box_frame(torch.from_numpy(xyz), torch.from_numpy(boxes))
        assert got.shape == (k, n, 3)
        np.testing.assert_allclose(got.numpy(), _numpy_frame(xyz, boxes), atol=1e-4)
        offsets = torch.from_numpy(xyz)[None] - torch.from_numpy(boxes)[:, None, :3]
        assert torch.equal(got, rotate_to_box_frame(offsets, torch.from_numpy(boxes)))  # same arithmetic


def test_inside_boxes_matches_numpy():
    rng = np.random.default_rng(1)
    xyz, boxes = rng.uniform(-12, 12, (3000, 3)).astype(np.float32), _boxes(rng, 9)
    local = _numpy_frame(xyz, boxes)
    for extra in (0.0, 0.5):
        ref = (np.abs(local) < (boxes[:, None, 3:6].astype(np.float64) + extra) / 2).all(-1)
        got = inside_boxes(torch.from_numpy(xyz), torch.from_numpy(boxes), extra)
        assert got.shape == (9, 3000) and ref.any()
        assert (got.numpy() != ref).mean() < 1e-3  # float32 against float64 at the faces
        same = inside_local(to_box_frame(torch.from_numpy(xyz), torch.from_numpy(boxes)), torch.from_numpy(boxes), extra)
        assert torch.equal(got, same)
