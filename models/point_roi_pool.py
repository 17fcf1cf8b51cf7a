"""PointRCNN's point RoI pooling with canonical transformation (OpenPCDet ``RoIPointPool3d``).

For every RoI (box row [x, y, z, l, w, h, yaw], LiDAR frame, geometric centre):

1. enlarge the box by ``extra_width`` metres in length, width and height (half on each side);
2. take the points inside the enlarged box, the first ``num_samples`` in point order; when
   fewer are inside, repeat them cyclically (slot j holds inside point j mod count), as the
   CUDA op does; a RoI with no point inside is flagged empty and gets zero rows;
3. express their coordinates in the RoI's canonical frame: centre subtracted, rotated by
   -yaw about +z (x along the RoI heading, y to its left, z up).

Everything is dense tensor algebra (broadcast transform, TopK, gather) so it exports to
standard ONNX ops and handles zero points or zero RoIs.

The second half holds the PointNet++ operators batched over RoIs that PointRCNN's refinement
network runs on the pooled points: farthest point sampling inside each RoI (a while_loop, an
ONNX Loop when exported), ball query and set abstraction.
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor, nn
from torch._higher_order_ops.while_loop import while_loop

from models.base import tracing
from models.pointnet2 import shared_mlp
from models.sparse import take_rows


def to_canonical(xyz: Tensor, rois: Tensor) -> Tensor:
    """Points (N, 3) expressed in the frame of every RoI (K, 7) -> (K, N, 3) metres."""
    return rotate_to_canonical(xyz[None, :, :] - rois[:, None, :3], rois)  # (K, N, 3)


def rotate_to_canonical(local: Tensor, rois: Tensor) -> Tensor:
    """(K, S, 3) points relative to RoI centres, rotated by -yaw of their RoI (K, 7)."""
    cos, sin = torch.cos(rois[:, 6])[:, None], torch.sin(rois[:, 6])[:, None]  # (K, 1)
    x = local[..., 0] * cos + local[..., 1] * sin  # rotation by -yaw
    y = -local[..., 0] * sin + local[..., 1] * cos
    return torch.stack([x, y, local[..., 2]], dim=-1)


def inside_rois(xyz: Tensor, rois: Tensor, extra_width: float = 0.0) -> Tensor:
    """(K, N) bool: point strictly inside the RoI enlarged by extra_width metres per dimension."""
    local = to_canonical(xyz, rois)  # (K, N, 3)
    half = (rois[:, 3:6] + extra_width) / 2  # (K, 3) half extents, m
    return (local.abs() < half[:, None, :]).all(dim=-1)


def sample_indices(inside: Tensor, num_samples: int) -> tuple[Tensor, Tensor]:
    """First ``num_samples`` inside points per RoI, repeated cyclically when fewer.

    inside (K, N) bool -> idx (K, num_samples) long in [0, N] (N for empty RoIs) and
    empty (K,) bool.
    """
    k, n = inside.shape
    order = torch.arange(n, device=inside.device).expand(k, n)  # (K, N)
    key = torch.where(inside, order, torch.full_like(order, n))
    key = torch.cat([key, key.new_full((k, num_samples), n)], dim=1)  # (K, N + S)
    first, _ = torch.topk(key, num_samples, dim=1, largest=False, sorted=True)  # (K, S)
    count = inside.sum(dim=1, keepdim=True)  # (K, 1)
    slot = torch.arange(num_samples, device=inside.device)[None, :]  # (1, S)
    cyclic = torch.remainder(slot, count.clamp(min=1))  # (K, S)
    idx = torch.gather(first, 1, cyclic)  # (K, S); all N for an empty RoI
    return idx, count[:, 0] == 0


def roi_point_pool(
    xyz: Tensor, feats: Tensor, rois: Tensor, num_samples: int, extra_width: float
) -> tuple[Tensor, Tensor]:
    """Pool the points of every RoI into its canonical frame.

    xyz (N, 3) m; feats (N, C); rois (K, 7). Returns pooled (K, S, 3 + C) = canonical xyz
    followed by the point features, and empty (K,) bool (pooled rows are zero for empty RoIs).
    """
    inside = inside_rois(xyz, rois, extra_width)  # (K, N)
    idx, empty = sample_indices(inside, num_samples)  # (K, S), (K,)
    table = torch.cat([xyz, feats], dim=1)  # (N, 3 + C)
    table = torch.cat([table, table.new_zeros(1, table.shape[1])], dim=0)  # (N + 1, 3 + C)
    rows = torch.index_select(table, 0, idx.reshape(-1)).reshape(idx.shape[0], num_samples, table.shape[1])
    local = rotate_to_canonical(rows[..., :3] - rois[:, None, :3], rois)  # (K, S, 3)
    keep = (~empty)[:, None, None].to(rows.dtype)  # (K, 1, 1)
    return torch.cat([local, rows[..., 3:]], dim=-1) * keep, empty


# ---- PointNet++ on the pooled points of every RoI (PointRCNN's refinement network) ----------


def _roi_fps_graph(xyz: Tensor, num: int) -> Tensor:
    """Batched FPS as a while_loop (exports to an ONNX Loop). xyz (K, S, 3) -> (K, num) long."""
    k = xyz.shape[0]
    rows = torch.arange(k, device=xyz.device)  # (K,)
    dist = xyz.new_full(xyz.shape[:2], float("inf"))  # (K, S) m^2 to the chosen set
    idx = torch.zeros(k, num, dtype=torch.long, device=xyz.device)
    last = torch.zeros(k, dtype=torch.long, device=xyz.device)
    step = torch.ones((), dtype=torch.long, device=xyz.device)

    def cond(i: Tensor, last: Tensor, idx: Tensor, dist: Tensor) -> Tensor:
        return i < num

    def body(i: Tensor, last: Tensor, idx: Tensor, dist: Tensor):
        centre = xyz[rows, last]  # (K, 3)
        dist = torch.minimum(dist, ((xyz - centre[:, None, :]) ** 2).sum(-1))  # (K, S)
        nxt = torch.argmax(dist, dim=1)  # (K,)
        col = i.reshape(1, 1).expand(k, 1)  # (K, 1)
        return i + 1, nxt, idx.scatter(1, col, nxt[:, None]), dist

    _, _, idx, _ = while_loop(cond, body, (step, last, idx, dist))
    return idx


def _roi_fps_eager(xyz: Tensor, num: int) -> Tensor:
    """Same arithmetic as _roi_fps_graph as a Python loop."""
    rows = torch.arange(xyz.shape[0], device=xyz.device)
    dist = xyz.new_full(xyz.shape[:2], float("inf"))
    idx = torch.zeros(xyz.shape[0], num, dtype=torch.long, device=xyz.device)
    last = idx[:, 0]
    for i in range(1, num):
        dist = torch.minimum(dist, ((xyz - xyz[rows, last][:, None, :]) ** 2).sum(-1))
        last = torch.argmax(dist, dim=1)
        idx[:, i] = last
    return idx


def roi_farthest_point_sample(xyz: Tensor, num: int) -> Tensor:
    """Farthest point sampling inside every RoI, starting from slot 0.

    xyz (K, S, 3) m with num <= S -> (K, num) long slot indices.
    """
    if num > xyz.shape[1]:
        raise ValueError(f"roi_farthest_point_sample: {num} samples from {xyz.shape[1]} slots")
    return _roi_fps_graph(xyz, num) if tracing() else _roi_fps_eager(xyz, num)


def roi_ball_query(xyz: Tensor, centres: Tensor, radius: float, nsample: int) -> Tensor:
    """First ``nsample`` slots within ``radius`` of each centre, padded with the first one.

    xyz (K, S, 3), centres (K, M, 3) with every centre one of the RoI's points (so each ball
    has a neighbour) -> (K, M, nsample) long slot indices.
    """
    s = xyz.shape[1]
    d2 = ((centres[:, :, None, :] - xyz[:, None, :, :]) ** 2).sum(-1)  # (K, M, S) m^2
    order = torch.arange(s, device=xyz.device).expand_as(d2)
    key = torch.where(d2 < radius * radius, order, torch.full_like(order, s))
    key = torch.cat([key, key.new_full(key.shape[:2] + (nsample,), s)], dim=2)  # (K, M, S + n)
    first, _ = torch.topk(key, nsample, dim=2, largest=False, sorted=True)  # (K, M, n)
    return torch.where(first < s, first, first[..., :1].expand_as(first)).clamp(max=s - 1)


def roi_gather(values: Tensor, idx: Tensor) -> Tensor:
    """values (K, S, C), idx (K, ...) slot indices -> (K, ..., C)."""
    k, s, c = values.shape
    # rows of the flattened (K * S, C) values: one Gather of whole rows in ONNX (a
    # GatherElements over (K, P, C) gathers element by element, and OpenVINO rejects it when
    # the exporter folds a channel slice of ``values`` into it)
    offset = (torch.arange(k, device=idx.device) * s).reshape(k, *([1] * (idx.dim() - 1)))
    return take_rows(values.reshape(k * s, c), idx + offset)


class RoISetAbstraction(nn.Module):
    """Set abstraction applied to the pooled points of every RoI independently.

    forward(xyz (K, S, 3), feats (K, S, C)) -> centres (K, M, 3), features (K, M, mlp[-1]).
    ``npoint=None`` groups all S points around the RoI centre (PointNet++'s "group all").
    """

    def __init__(self, npoint: int | None, radius: float, nsample: int, mlp: Sequence[int]):
        super().__init__()
        self.npoint, self.radius, self.nsample = npoint, radius, nsample
        self.mlp = shared_mlp([mlp[0] + 3, *mlp[1:]])

    def forward(self, xyz: Tensor, feats: Tensor) -> tuple[Tensor, Tensor]:
        if self.npoint is None:
            centres = xyz.new_zeros(xyz.shape[0], 1, 3)  # (K, 1, 3) RoI origin
            grouped = torch.cat([xyz, feats], -1)[:, None]  # (K, 1, S, 3 + C)
        else:
            centres = roi_gather(xyz, roi_farthest_point_sample(xyz, self.npoint))  # (K, M, 3)
            idx = roi_ball_query(xyz, centres, self.radius, self.nsample)  # (K, M, n)
            rel = roi_gather(xyz, idx) - centres[:, :, None, :]  # (K, M, n, 3) m
            grouped = torch.cat([rel, roi_gather(feats, idx)], -1)  # (K, M, n, 3 + C)
        return centres, self.mlp(grouped).amax(2)  # (K, M, 3), (K, M, C_out)
