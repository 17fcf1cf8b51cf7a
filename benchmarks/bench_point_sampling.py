"""PointRCNN's point sampling on simulated frames: how many of a car's points survive it, by
distance, and how far apart the first set-abstraction centres lie against their radii.

Per car (label class Car, at least 5 in-range points): its in-range points and those kept by
``PointRCNN.points_of_interest``; per reference distance (cars within 2 m of it) the median of
both. Per frame: the in-range points and those beyond ``far_depth``, and the nearest-neighbour
spacing of the first level's farthest-point-sampling centres (median, and near / far of 40 m).

    python benchmarks/bench_point_sampling.py --data DIR [--profile compact] [--num-points N]
        [--sa-npoints N:r1,r2] [--frames 12] [--split train]
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import torch

from harness.core.boxes import points_in_boxes
from harness.dataset import KittiDataset
from models.point_rcnn import CONFIGS, PointRCNN
from models.pointnet2 import farthest_point_sample
from models.voxelize import range_mask

DISTANCES = (6.0, 12.0, 21.0, 45.0)  # m, near and far cars of the SOTIF frames


def car_counts(model: PointRCNN, sample) -> list[tuple[float, int, int]]:
    """(distance m, in-range points, kept points) of every car of the frame with >= 5 points."""
    points = torch.from_numpy(sample.points)
    inside = sample.points[range_mask(points, model.cfg.pc_range).numpy()]
    kept, _ = model.points_of_interest(points)
    kept = np.unique(kept.numpy(), axis=0)  # repeats (a sparse frame) count once
    cars = sample.boxes_of("Car")
    if not len(cars):
        return []
    raw_in = points_in_boxes(inside[:, :3], cars).sum(0)  # (G,)
    kept_in = points_in_boxes(kept[:, :3], cars).sum(0)
    dist = np.linalg.norm(cars[:, :2], axis=1)
    return [(float(d), int(r), int(k)) for d, r, k in zip(dist, raw_in, kept_in) if r >= 5]


def centre_spacing(model: PointRCNN, sample) -> tuple[float, float, float, float]:
    """Median nearest-neighbour distance (m) of the first level's centres (all, within far_depth
    of the sensor, beyond it) and the share of the sampled points within the level's largest
    radius of some centre (the points its set abstraction sees)."""
    kept, _ = model.points_of_interest(torch.from_numpy(sample.points))
    xyz = torch.unique(kept[:, :3], dim=0)
    centres = xyz[farthest_point_sample(xyz, min(model.cfg.sa_npoints[0], len(xyz)))]
    d2 = ((centres[:, None, :] - centres[None, :, :]) ** 2).sum(-1).numpy()
    np.fill_diagonal(d2, np.inf)
    nn = np.sqrt(d2.min(1))
    far = np.linalg.norm(centres.numpy(), axis=1) >= model.cfg.far_depth
    seen = float((torch.cdist(xyz, centres).min(1).values <= max(model.cfg.sa_radii[0])).float().mean())
    med = lambda v: float(np.median(v)) if len(v) else float("nan")
    return med(nn), med(nn[~far]), med(nn[far]), seen


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--split", default="train")
    ap.add_argument("--profile", default="compact", choices=sorted(CONFIGS))
    ap.add_argument("--num-points", type=int, default=None, help="override the profile's num_points")
    ap.add_argument("--sa-npoints", default=None, help="override the first level's centres and radii: N:r1,r2")
    ap.add_argument("--frames", type=int, default=12)
    args = ap.parse_args()
    cfg = CONFIGS[args.profile]
    if args.num_points:
        cfg = dataclasses.replace(cfg, num_points=args.num_points)
    if args.sa_npoints:
        n, radii = args.sa_npoints.split(":")
        cfg = dataclasses.replace(cfg, sa_npoints=(int(n), *cfg.sa_npoints[1:]),
                                  sa_radii=(tuple(float(r) for r in radii.split(",")), *cfg.sa_radii[1:]))
    model = PointRCNN(cfg).eval()
    ds = KittiDataset(args.data, args.split)
    cars, frames, spacing = [], [], []
    with torch.no_grad():
        for i in range(min(args.frames, len(ds))):
            s = ds[i]
            cars += car_counts(model, s)
            inside = s.points[range_mask(torch.from_numpy(s.points), cfg.pc_range).numpy()]
            frames.append((len(inside), int((np.linalg.norm(inside[:, :3], axis=1) >= cfg.far_depth).sum())))
            spacing.append(centre_spacing(model, s))
    f = np.array(frames)
    print(f"{args.profile} num_points={cfg.num_points}, {len(frames)} frames: in-range points median "
          f"{np.median(f[:, 0]):.0f}, of them beyond {cfg.far_depth:.0f} m median {np.median(f[:, 1]):.0f}")
    c = np.array(cars)
    for d in DISTANCES:
        sel = c[np.abs(c[:, 0] - d) <= 2.0] if len(c) else c
        if len(sel):
            share = np.median(sel[:, 2] / sel[:, 1])
            print(f"  car at {d:4.0f} +- 2 m ({len(sel):2d} cars): points median {np.median(sel[:, 1]):6.0f}, "
                  f"kept median {np.median(sel[:, 2]):5.0f} (median share {share:.3f})")
    sp = np.nanmedian(np.array(spacing), axis=0)
    print(f"  first SA level: {cfg.sa_npoints[0]} centres, nearest-neighbour spacing median {sp[0]:.2f} m "
          f"(< {cfg.far_depth:.0f} m: {sp[1]:.2f}, beyond: {sp[2]:.2f}); radii {cfg.sa_radii[0]} m; "
          f"{sp[3]:.0%} of the sampled points within {max(cfg.sa_radii[0])} m of a centre")


if __name__ == "__main__":
    main()
