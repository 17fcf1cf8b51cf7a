"""Export seconds per model, cold and with its traced graph cached, and the proof that the cached
export is the fresh one byte for byte.

For each model: two checkpoints written as training writes them (random weights, seeds 0 and 1,
the second with random BatchNorm statistics), then three ``sotif-bench export`` processes, timed
from the outside: checkpoint 0 with an empty graph cache (cold: traces, fills the cache),
checkpoint 1 with the cache (warm), checkpoint 1 with the cache off (fresh); the warm and fresh
files must be equal.

    python -m benchmarks.bench_export --profile compact --out /tmp/bench_export [--models a,b]
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import time
from pathlib import Path

import torch

from models import zoo


def write_checkpoint(name: str, profile: str, seed: int, path: Path) -> None:
    """A checkpoint with the keys ``harness.train.train`` writes that ``load_checkpoint`` reads."""
    torch.manual_seed(seed)
    model = zoo.build(name, profile)
    if seed:
        with torch.no_grad():
            for buf in model.buffers():
                if buf.is_floating_point():
                    buf.uniform_(0.5, 1.5)  # BatchNorm statistics a training would have moved
    torch.save({"model": name, "profile": profile, "config": dataclasses.asdict(zoo.config(name, profile)),
                "state_dict": model.state_dict(), "epoch": 1, "data_hash": "", "config_hash": ""}, path)


def timed_export(name: str, ckpt: Path, out: Path, cache: str) -> float:
    env = {**os.environ, "SOTIF_BENCH_GRAPH_CACHE": cache}
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "harness.cli", "export", "--model", name, "--checkpoint", str(ckpt),
                    "--out", str(out), "--force", "--quiet"], env=env, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--profile", default="compact", choices=zoo.PROFILES)
    p.add_argument("--models", default=",".join(zoo.MODEL_NAMES))
    p.add_argument("--out", type=Path, required=True)
    a = p.parse_args()
    cache = a.out / "graphs"
    print(f"{'model':14s} {'cold s':>7s} {'warm s':>7s} {'fresh s':>8s}  warm == fresh", flush=True)
    for name in a.models.split(","):
        folder = a.out / name
        folder.mkdir(parents=True, exist_ok=True)
        for seed in (0, 1):
            write_checkpoint(name, a.profile, seed, folder / f"c{seed}.pt")
        cold = timed_export(name, folder / "c0.pt", folder / "cold.onnx", str(cache))
        warm = timed_export(name, folder / "c1.pt", folder / "warm.onnx", str(cache))
        fresh = timed_export(name, folder / "c1.pt", folder / "fresh.onnx", "off")
        same = (folder / "warm.onnx").read_bytes() == (folder / "fresh.onnx").read_bytes()
        print(f"{name:14s} {cold:7.1f} {warm:7.1f} {fresh:8.1f}  {'yes' if same else 'NO'}", flush=True)


if __name__ == "__main__":
    main()
