"""Seconds per training step of this checkout against another (``--base``), measured side by side:
one process per checkout (its code, one thread) takes the model's training steps in lockstep
with the other, step by step in the order A B B A A B ..., both on the same batch, so that the
shared machine's drift falls on both alike. Both start from the same weights and seeds.
``--amp bf16``: this checkout's steps run under the training's autocast (``train --amp bf16``);
without ``--base`` the base is this checkout in float32, so that the pair measures the lever alone.

    python benchmarks/paired_train_step.py [--base DIR] --data DIR [--models a,b] [--steps 8] [--amp bf16]
        [--losses]

Prints per model the mean seconds per step of each checkout, the median of the per-step ratios
with the range of the middle half, and the training core-seconds they make on the default run's
schedule: seconds per step x the compact profile's epochs x ceil(255 / 2) steps per epoch (the
default run's 300 training scenes keep 255 for training). ``--losses``: then each step's loss in both,
the same batches from the same weights at the one-cycle schedule's first rate (with ``--warmup 0``, a
training's first steps).
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
    from models.zoo import resolve
    tcfg = resolve(name, "compact").schedule
    return tcfg.epochs * math.ceil(DEFAULT_TRAIN_FRAMES / tcfg.batch_size)


def serve(code: Path, data: Path, name: str, warmup: int, amp: str = "") -> subprocess.Popen:
    """A process that takes ``name``'s training steps with the code of the checkout ``code`` (under ``amp``'s
    autocast when given)."""
    env = {**os.environ, "PYTHONPATH": str(code), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, str(HERE / "profile_train_step.py"), "--serve", "--data", str(data),
                             "--models", name, "--warmup", str(warmup), *(["--amp", amp] if amp else [])],
                            env=env, cwd=code, text=True,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    assert proc.stdout.readline().strip() == "ready", f"{code}: the step server did not start"
    return proc


def step(proc: subprocess.Popen, k: int) -> tuple[float, float]:
    """Seconds and loss of step ``k``."""
    proc.stdin.write(f"{k}\n")
    proc.stdin.flush()
    seconds, loss = proc.stdout.readline().split()
    return float(seconds), float(loss)


def paired(base: Path, new: Path, data: Path, name: str, warmup: int, steps: int,
           amp: str = "") -> tuple[np.ndarray, np.ndarray]:
    """Seconds and losses (2, steps) of steps warmup .. warmup + steps - 1 with each checkout's code, taken
    alternately (``new``'s under ``amp``'s autocast)."""
    procs = [serve(base, data, name, warmup), serve(new, data, name, warmup, amp)]
    times, losses = np.zeros((2, steps)), np.zeros((2, steps))
    try:
        for k in range(steps):
            for who in ((0, 1) if k % 2 == 0 else (1, 0)):
                times[who, k], losses[who, k] = step(procs[who], warmup + k)
    finally:
        for proc in procs:
            proc.stdin.close()
            proc.wait()
    return times, losses


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--base", type=Path, default=HERE.parent,
                   help="the other checkout (its code is timed as 'base'; default: this one, in float32)")
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--models", default=",".join(zoo.MODEL_NAMES))
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--steps", type=int, default=8)
    p.add_argument("--amp", choices=["bf16"], help="this checkout's steps under the training's autocast (train --amp)")
    p.add_argument("--losses", action="store_true", help="also print each step's loss in both")
    args = p.parse_args(argv)
    new = HERE.parent
    print("| model | base s/step | new s/step | new / base (middle half) | steps | base core-s | new core-s |\n"
          "|---|---:|---:|---:|---:|---:|---:|")
    trajectories = {}
    for name in args.models.split(","):
        (base, ours), trajectories[name] = paired(args.base.resolve(), new, args.data.resolve(), name, args.warmup,
                                                  args.steps, args.amp or "")
        q1, med, q3 = np.percentile(ours / base, [25, 50, 75])
        b, n, steps = base.mean(), ours.mean(), schedule_steps(name)
        print(f"| {name} | {b:.3f} | {n:.3f} | {med:.2f} ({q1:.2f}-{q3:.2f}) | {steps} | {b * steps:,.0f} | "
              f"{n * steps:,.0f} |", flush=True)
    if args.losses:
        print("\n| model | step | base loss | new loss | new / base |\n|---|---:|---:|---:|---:|")
        for name, (base, ours) in trajectories.items():
            for k in range(args.steps):
                print(f"| {name} | {args.warmup + k + 1} | {base[k]:.4f} | {ours[k]:.4f} | {ours[k] / base[k]:.4f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
