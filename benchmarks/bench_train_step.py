"""Training-step time of the sparse-conv models: sparse convs as one gather + GEMM over the
whole (V, 27, C) neighbour table (``models.sparse.table_gemm``, the inference form) against one GEMM per kernel offset over
the occupied entries (``models.sparse.pair_gemm``, what training uses).

    python -m benchmarks.bench_train_step [--data DIR] [--models second,dv_second,parta2,pv_rcnn,mvx_net]
        [--steps 4] [--threads 1]

Both forms run the same batches (batch 2, augmented, ground-truth sampling for LiDAR-only
models) from the same initial weights; the first step of each is a warm-up. Without ``--data``
a 20-frame training set is simulated under a temporary directory.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import models.sparse as sparse
from harness.augment import AugmentConfig, augment
from harness.dataset import KittiDataset
from harness.gt_database import load_or_build
from models import zoo


def seconds_per_step(name: str, data: Path, steps: int, form) -> float:
    """Mean seconds of a training step (forward, backward, AdamW) after one warm-up step."""
    torch.manual_seed(0)
    net = zoo.build(name, "compact")
    net.train()
    ds = KittiDataset(data, "train", with_image=net.uses_camera)
    aug = AugmentConfig()
    database = None if net.uses_camera else load_or_build(data, data / "gt_database", aug.gt_sampling)
    rng = np.random.default_rng(0)
    batches = [[augment(ds[(2 * k + j) % len(ds)], rng, aug, database) for j in (0, 1)] for k in range(steps + 1)]
    optimizer = torch.optim.AdamW(net.parameters(), lr=1e-3)
    original = sparse.pair_gemm
    sparse.pair_gemm = form if form is original else (lambda f, t, w, pairs=None: form(f, t, w))
    try:
        times = []
        for batch in batches:
            t0 = time.perf_counter()
            loss = net.loss(batch)["loss"]
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            times.append(time.perf_counter() - t0)
    finally:
        sparse.pair_gemm = original
    return float(np.mean(times[1:]))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, help="a training set (sotif-bench simulate --preset train)")
    p.add_argument("--models", default="second,dv_second,parta2,pv_rcnn,mvx_net")
    p.add_argument("--steps", type=int, default=4)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            from simulator import generate
            data = generate(Path(tmp) / "train", preset="train", frames=20, seed=0, progress=False)
        print("| model | s/step one GEMM | s/step by offset | speed-up |\n|---|---:|---:|---:|")
        for name in args.models.split(","):
            full = seconds_per_step(name, Path(data), args.steps, sparse.table_gemm)
            pairs = seconds_per_step(name, Path(data), args.steps, sparse.pair_gemm)
            print(f"| {name} | {full:.2f} | {pairs:.2f} | {full / pairs:.2f}x |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
