"""Seconds per training step with some of a model's modules under ``torch.compile`` (inductor, static shapes)
against the same steps eager, in one process and one thread: rounds of 4 eager steps then 4 compiled ones
(the stepper of ``benchmarks/profile_train_step.py``: the default profile, epoch 0's batches, seed 0).

    python -m benchmarks.compile_train_step --data DIR [--model pointpillars] [--modules backbone2d,head]
        [--rounds 3]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from profile_train_step import Stepper  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, required=True, help="a training set (simulate --preset train)")
    p.add_argument("--model", default="pointpillars")
    p.add_argument("--modules", default="backbone2d,head", help="the model's attributes to compile")
    p.add_argument("--rounds", type=int, default=3)
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    stepper = Stepper(a.model, a.data)
    eager = {name: getattr(stepper.net, name) for name in a.modules.split(",")}
    compiled = {name: torch.compile(module, dynamic=False) for name, module in eager.items()}

    def steps(first: int, n: int, modules: dict) -> float:
        for name, module in modules.items():
            setattr(stepper.net, name, module)
        t0 = time.perf_counter()
        for k in range(first, first + n):
            stepper.step(k)
        return (time.perf_counter() - t0) / n

    steps(0, 2, eager)
    t0 = time.perf_counter()
    steps(2, 2, compiled)
    print(f"{a.model}, {a.modules} compiled: first two compiled steps {time.perf_counter() - t0:.0f} s", flush=True)
    for r in range(a.rounds):
        plain, fast = steps(4 + 8 * r, 4, eager), steps(8 + 8 * r, 4, compiled)
        print(f"round {r}: eager {plain:.3f} s/step, compiled {fast:.3f} s/step, ratio {fast / plain:.2f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
