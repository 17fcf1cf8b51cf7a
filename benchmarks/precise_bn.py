"""How much of a trained model's val AP its BatchNorm running statistics cost.

Frames run one by one through every model, so each BatchNorm call normalises one frame, and
training keeps the running mean and variance as an exponential average over frames (momentum 0.01
in the voxel networks, 0.1 in the PointNet++ layers and RoI heads, which then follow the last ten
or so frames of weights that have since moved). "Precise BN" (Wu & Johnson, "Rethinking
'Batch' in BatchNorm", 2021; fvcore's ``update_bn_stats``, torch's ``swa_utils.update_bn``)
re-estimates them with the weights frozen: the plain average over N training frames. Here the
frames run through the model in inference mode (the proposals the exported graph makes, no
labels), with only the BatchNorm layers collecting statistics. ``--first-stage`` leaves the
layers of a two-stage model's RoI head as trained (their statistics are of sampled training
RoIs, the distribution the head's weights were fitted to). ``--augment`` feeds the frames as
training sees them: flipped, rotated and scaled, with pasted ground-truth objects for the LiDAR-only
models (the statistics training itself averages), instead of as they were recorded.

Prints val AP40 (3D / BEV moderate, IoU 0.7, the run's 45 val frames) before and after, per
model. Nothing is written: a measurement, not a change of the run's checkpoints.

    python -m benchmarks.precise_bn RUN_DIR [--models a,b] [--frames 60] [--first-stage] [--augment]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from torch import nn

from harness.augment import AugmentConfig, augment
from harness.dataset import KittiDataset
from harness.gt_database import load_or_build
from harness.train import eager_inputs, uses_gt_sampling, validation_ap
from models.zoo import load_checkpoint

# the first-stage modules of the two-stage models (their RoI heads are the other top-level modules)
FIRST_STAGE = {"parta2": ("backbone2d", "unet"), "pv_rcnn": ("backbone2d", "backbone3d"),
               "point_rcnn": ("backbone", "seg_head", "box_head")}


def batch_norms(net: nn.Module, prefixes: tuple[str, ...] | None = None) -> list[nn.modules.batchnorm._BatchNorm]:
    """The BatchNorm layers of ``net`` (those under the top-level modules ``prefixes`` if given)."""
    return [m for name, m in net.named_modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)
            and (prefixes is None or name.split(".")[0] in prefixes)]


def recompute_bn_stats(net: nn.Module, inputs, layers: list[nn.modules.batchnorm._BatchNorm]) -> int:
    """Replace the running statistics of ``layers`` by the plain average of their per-call batch
    statistics over ``inputs`` (an iterable of argument tuples), the rest of ``net`` in eval mode;
    torch's cumulative average (momentum None). Returns the number of forward calls."""
    for m in layers:
        m.reset_running_stats()
        m.momentum = None
    net.eval()
    for m in layers:
        m.train()
    calls = 0
    with torch.no_grad():
        for args in inputs:
            net(*args)
            calls += 1
    net.eval()
    return calls


def frame_inputs(ds: KittiDataset, n: int, camera: bool, aug: AugmentConfig | None = None, database=None,
                 seed: int = 0):
    """The eager model's arguments for the first ``n`` frames of ``ds``; with ``aug``, each frame
    augmented as in training (its own generator, ``[seed, i]``; ``database``: objects to paste)."""
    for i in range(min(n, len(ds))):
        sample = ds[i] if aug is None else augment(ds[i], np.random.default_rng([seed, i]), aug, database)
        yield eager_inputs(sample, camera)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", type=Path)
    p.add_argument("--models", default="pointpillars,second,dv_second,parta2,pv_rcnn,point_rcnn,mvx_net")
    p.add_argument("--frames", type=int, default=60, help="training frames to average over")
    p.add_argument("--first-stage", action="store_true", help="two-stage models: the first stage's layers only")
    p.add_argument("--augment", action="store_true", help="the frames augmented as in training (pasting included "
                   "for LiDAR-only models)")
    args = p.parse_args(argv)
    data = args.run / "data" / "train"
    print(f"val AP40 @0.7 moderate ({data}, val split) before -> after re-estimating BatchNorm statistics "
          f"on {args.frames} {'augmented ' if args.augment else ''}training frames")
    print("| model | BatchNorm layers | 3D | BEV | 3D all distances |")
    print("|---|---|---|---|---|")
    for name in args.models.split(","):
        net, _ = load_checkpoint(args.run / "models" / name / "checkpoint.pt")
        before = validation_ap(net, data)
        layers = batch_norms(net, FIRST_STAGE.get(name) if args.first_stage else None)
        camera = getattr(net, "uses_camera", False)
        aug = AugmentConfig() if args.augment else None
        database = (load_or_build(data, data / "gt_database", aug.gt_sampling)
                    if aug is not None and uses_gt_sampling(net, aug) else None)
        frames = frame_inputs(KittiDataset(data, "train", with_image=camera), args.frames, camera, aug, database)
        recompute_bn_stats(net, frames, layers)
        after = validation_ap(net, data)
        cells = " | ".join(f"{before[k]:.1f} -> {after[k]:.1f}" for k in ("3d_moderate", "bev_moderate", "3d_all"))
        print(f"| {name} | {len(layers)} | {cells} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
