"""What every detector offers the harness.

A detector is an ``nn.Module`` built from a frozen config dataclass. The harness only uses:

- ``forward(points[, image, lidar2img])`` -> the ONNX contract outputs, as a tuple of tensors:
  ``(boxes (M, 7), scores (M,))`` for one-stage models and
  ``(boxes, scores, rois (K, 7), roi_scores (K,), rcnn_boxes (K, 7))`` for two-stage models
  (``rcnn_boxes``: the refined box of every RoI before score threshold and NMS, for
  OpenPCDet-style Recall at RCNN). One frame, no batch axis, LiDAR frame, final NMS inside.
- ``loss(samples)`` -> dict of scalar tensors with the total under ``"loss"``.
- the class attributes below (written into the ONNX metadata).
- ``sampling_rng``: the numpy generator of a model's training draws beyond torch's (the
  two-stage models' RoI sampling); the trainer reseeds it every epoch, so that a resumed
  training draws as an uninterrupted one.
"""
from __future__ import annotations

import contextlib
from typing import Iterable

import numpy as np
import torch
from torch import Tensor, nn

ONE_STAGE_OUTPUTS = ("boxes", "scores")
TWO_STAGE_OUTPUTS = ("boxes", "scores", "rois", "roi_scores", "rcnn_boxes")


def tracing() -> bool:
    """True while torch.export / torch.compile traces a graph (ONNX export): code that has an
    eager fast path and a graph form takes the graph form."""
    return torch.compiler.is_exporting() or torch.compiler.is_compiling()


def training_form() -> bool:
    """True in eager mode with autograd on: code with a faster-to-train form of an op (same values
    and gradients as its inference / graph form) takes that one."""
    return torch.is_grad_enabled() and not tracing()


def no_autocast(device: str = "cpu"):
    """A context with autocast off, for what stays float32 under ``train --amp bf16``: coordinates that a matmul
    computes (a bfloat16 pixel coordinate near 1,000 px is off by up to 4 px) and the sparse convolutions
    (``models.sparse.gather_gemm``). Nothing where autocast is off (inference, export: the graph is unchanged)."""
    if torch.is_autocast_enabled(device):
        return torch.autocast(device, enabled=False)
    return contextlib.nullcontext()


def reset_norm_statistics(model: nn.Module) -> None:
    """Clear every BatchNorm's running statistics and make them a cumulative average of the passes to come."""
    for m in model.modules():
        if isinstance(m, nn.modules.batchnorm._BatchNorm):
            m.reset_running_stats()
            m.momentum = None


def mean_over_frames(frame_losses: Iterable[dict[str, Tensor]], frames: int) -> dict[str, Tensor]:
    """Each loss term averaged over the frames of a batch (frames run one by one: no batch axis)."""
    totals: dict[str, Tensor] = {}
    for losses in frame_losses:
        for k, v in losses.items():
            totals[k] = totals.get(k, 0.0) + v / frames
    return totals


class Detector(nn.Module):
    architecture: str = ""  # the model name used on the command line, e.g. "pointpillars"
    two_stage: bool = False
    uses_camera: bool = False
    sampling_rng: np.random.Generator | None = None  # set by two-stage models; see the module docstring

    @property
    def output_names(self) -> tuple[str, ...]:
        return TWO_STAGE_OUTPUTS if self.two_stage else ONE_STAGE_OUTPUTS

    @property
    def input_names(self) -> tuple[str, ...]:
        return ("points", "image", "lidar2img") if self.uses_camera else ("points",)
