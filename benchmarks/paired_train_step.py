"""Seconds per training step of this checkout against another (``--base``), measured side by side:
each round runs ``profile_train_step --time`` once with each checkout's code, in fresh processes
on one thread, alternating which goes first (A B B A ...), so that the machine's drift falls on
both alike. The same batches, weights and seeds in both.

    python benchmarks/paired_train_step.py --base DIR --data DIR [--models a,b] [--rounds 2]

Prints per model the median over rounds of each checkout's seconds per step, their ratio (the
median of the per-round ratios) and the training core-seconds they make on the default run's
schedule: seconds per step x the compact profile's epochs x ceil(255 / 2) steps per epoch (the
default run's 300 training scenes keep 255 for training).
"""
from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from models import zoo

DEFAULT_TRAIN_FRAMES = 255
HERE = Path(__file__).resolve().parent


def schedule_steps(name: str) -> int:
    from harness.train import train_config
    tcfg = train_config(name, "compact")
    return tcfg.epochs * math.ceil(DEFAULT_TRAIN_FRAMES / tcfg.batch_size)


def time_checkout(code: Path, data: Path, name: str, warmup: int, steps: int) -> float:
    """Seconds per step of ``name`` with the code of the checkout ``code``."""
    env = {**os.environ, "PYTHONPATH": str(code), "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, str(HERE / "profile_train_step.py"), "--time", "--data", str(data),
                          "--models", name, "--warmup", str(warmup), "--steps", str(steps)],
                         env=env, cwd=code, check=True, capture_output=True, text=True).stdout
    return float(out.split()[-1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--base", type=Path, required=True, help="the other checkout (its code is timed as 'base')")
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--models", default=",".join(zoo.MODEL_NAMES))
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--steps", type=int, default=4)
    args = p.parse_args(argv)
    new = HERE.parent
    print("| model | base s/step | new s/step | new / base | steps | base core-s | new core-s |\n|---|---:|---:|---:|---:|---:|---:|")
    for name in args.models.split(","):
        base, ours = [], []
        for r in range(args.rounds):
            order = [(args.base, base), (new, ours)]
            for code, times in order if r % 2 == 0 else order[::-1]:
                times.append(time_checkout(code, args.data.resolve(), name, args.warmup, args.steps))
        b, n = float(np.median(base)), float(np.median(ours))
        ratio = float(np.median(np.array(ours) / np.array(base)))
        steps = schedule_steps(name)
        print(f"| {name} | {b:.3f} | {n:.3f} | {ratio:.2f} | {steps} | {b * steps:,.0f} | {n * steps:,.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
