"""Training levers measured by draws: each model trained with seeds 0..K-1 with and without a lever, and the
spread of its val AP40 3D moderate (and, with ``--headline``, of the eager model's headline AP40 3D on a SOTIF
set's test frames) over the draws. A lever is adopted when it narrows the spread at no loss of mean; a lever
that saves time (``amp``) when its mean is not lower.

    python benchmarks/levers.py --data RUN/data/train [--headline RUN/data/sotif] [--models second,pointpillars]
        [--levers ema,amp] [--seeds 2] [--out /tmp/levers]

Levers: ``ema`` (Schedule.ema = 0.999: the exponential moving average of the weights, evaluated and exported);
``amp`` (Schedule.amp = "bf16": each step's forward pass and loss under bfloat16 autocast, ``harness.amp``; only on
a CPU with native bf16, refused elsewhere).
Each training is ``harness.train.train`` on the compact profile (the default run's), one thread, its checkpoint
under ``--out/<model>-<lever>-seed<k>`` (an interrupted benchmark resumes every training). Prints a Markdown
table: model, lever, draws, val mean / min / max, headline mean / min / max, training seconds per draw.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from harness.train import train, validation_ap
from models import zoo

LEVERS = {"none": {}, "ema": {"ema": 0.999}, "amp": {"amp": "bf16"}}


def draw(model: str, lever: str, seed: int, data: Path, out: Path, headline: Path | None, profile: str) -> dict:
    recipe = zoo.resolve(model, profile)
    recipe = replace(recipe, schedule=replace(recipe.schedule, **LEVERS[lever]))
    ckpt = train(recipe, data, out / f"{model}-{lever}-seed{seed}", seed=seed, progress=False)
    state = zoo.read_checkpoint(ckpt)
    row = {"val": state["val_ap"]["3d_moderate"], "seconds": state["train_seconds"]}
    if headline is not None:
        net, _ = zoo.load_checkpoint(ckpt)
        row["headline"] = validation_ap(net, headline, split="test")["3d_all"]
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, required=True, help="a training set with a val split (a run's data/train)")
    p.add_argument("--headline", type=Path, help="a SOTIF set whose test frames give the headline AP (optional)")
    p.add_argument("--models", default="second,pointpillars")
    p.add_argument("--levers", default="ema", help=f"comma-separated, of {', '.join(l for l in LEVERS if l != 'none')}")
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--profile", default="compact")
    p.add_argument("--out", type=Path, default=Path("/tmp/levers"))
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    print("| model | lever | draws | val mean | val min | val max | headline mean | headline min | headline max "
          "| train s / draw |\n|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for model in a.models.split(","):
        for lever in ["none", *a.levers.split(",")]:
            rows = [draw(model, lever, s, a.data, a.out, a.headline, a.profile) for s in range(a.seeds)]
            val = np.array([r["val"] for r in rows])
            head = np.array([r.get("headline", np.nan) for r in rows])
            print(f"| {model} | {lever} | {len(rows)} | {val.mean():.2f} | {val.min():.2f} | {val.max():.2f} | "
                  f"{head.mean():.2f} | {head.min():.2f} | {head.max():.2f} | "
                  f"{np.mean([r['seconds'] for r in rows]):.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
