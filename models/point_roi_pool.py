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

The second half holds the set abstraction that PointRCNN's refinement network runs on the pooled
points of every RoI at once (FPS and ball query batched over RoIs, from models/pointnet2.py).
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor, nn

from models.box_frame import inside_boxes, rotate_to_box_frame
from models.pointnet2 import ball_queries, farthest_point_sample, shared_mlp
from models.voxelize import take_rows


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
    inside = inside_boxes(xyz, rois, extra_width)  # (K, N)
    idx, empty = sample_indices(inside, num_samples)  # (K, S), (K,)
    table = torch.cat([xyz, feats], dim=1)  # (N, 3 + C)
    table = torch.cat([table, table.new_zeros(1, table.shape[1])], dim=0)  # (N + 1, 3 + C)
    rows = torch.index_select(table, 0, idx.reshape(-1)).reshape(idx.shape[0], num_samples, table.shape[1])
    local = rotate_to_box_frame(rows[..., :3] - rois[:, None, :3], rois)  # (K, S, 3)
    keep = (~empty)[:, None, None].to(rows.dtype)  # (K, 1, 1)
    return torch.cat([local, rows[..., 3:]], dim=-1) * keep, empty


# ---- PointNet++ on the pooled points of every RoI (PointRCNN's refinement network) ----------


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
            centres = roi_gather(xyz, farthest_point_sample(xyz, self.npoint))  # (K, M, 3)
            idx, _ = ball_queries(xyz, centres, (self.radius,), (self.nsample,))[0]  # (K, M, n)
            idx = idx.clamp(max=xyz.shape[1] - 1)  # every centre is a RoI point: never empty
            rel = roi_gather(xyz, idx) - centres[:, :, None, :]  # (K, M, n, 3) m
            grouped = torch.cat([rel, roi_gather(feats, idx)], -1)  # (K, M, n, 3 + C)
        return centres, self.mlp(grouped).amax(2)  # (K, M, 3), (K, M, C_out)
