"""The seeded rules that fill a reference checkpoint's tensors with random values (golden data of
``benchmarks/golden_published.py``; the tests rebuild the same file from the stored rule, names, shapes
and seed). numpy's PCG64, one stream per checkpoint: the same values on every machine.

``golden-weights-1``, per tensor in the checkpoint's order, drawn in float64 and cast to float32:
BatchNorm ``running_mean`` N(0, 0.1^2), ``running_var``, and any other 1-D ``weight`` (BatchNorm's scale)
U(0.5, 1.5); a 1-D ``bias`` N(0, 0.1^2) (the class-logit bias of the head N(cls_bias, 0.1^2), so that a
few anchors score above 0.1); a weight of rank >= 2 N(0, 2 / fan_in) with fan_in = numel / shape[0],
times ``head_scale`` in the dense head (``dense_head.*``: PointPillars' bird's-eye map reaches ~80, so
that its logits and box residuals stay in range); integer counters 0.

``golden-weights-2``: as golden-weights-1, but a weight of rank >= 2 with more than ``LARGE`` (2^20)
elements is uniform with the same variance, U(-a, a) with a = sqrt(3 * 2 / fan_in) (times ``head_scale``
in the dense head), drawn in float32: ``u = rng.random(n, dtype=float32)`` in [0, 1), then
``u * float32(2 a) - float32(a)``, each step rounded to float32. A float32 uniform costs about a tenth of
a float64 normal and its cast: Part-A2's RCNN layer of 56.6 M weights is filled in well under a second.
"""
from __future__ import annotations

import numpy as np

RULES = ("golden-weights-1", "golden-weights-2")
RULE = RULES[0]  # PointPillars', SECOND's and DV-SECOND's golden files
LARGE = 1 << 20  # golden-weights-2: a weight tensor above this many elements is drawn uniform in float32


def fill(names: list[str], shapes: list[tuple[int, ...]], seed: int, cls_bias: float,
         head_scale: float = 1.0, rule: str = RULE) -> dict[str, np.ndarray]:
    """{name: array} in the checkpoint's layout by the seeded ``rule``; integer tensors (num_batches_tracked,
    global_step) int64."""
    if rule not in RULES:
        raise ValueError(f"unknown weight rule {rule!r}: one of {', '.join(RULES)}")
    rng = np.random.Generator(np.random.PCG64(seed))
    out = {}
    for name, shape in zip(names, shapes):
        leaf = name.rsplit(".", 1)[-1]
        n = int(np.prod(shape)) if shape else 1
        if leaf in ("num_batches_tracked", "global_step"):
            out[name] = np.zeros(shape, np.int64)
            continue
        if leaf == "running_mean":
            v = rng.normal(0.0, 0.1, n)
        elif leaf in ("running_var", "weight") and len(shape) == 1:
            v = rng.uniform(0.5, 1.5, n)
        elif leaf == "bias":
            v = rng.normal(cls_bias if "conv_cls" in name else 0.0, 0.1, n)
        else:
            scale = head_scale if name.startswith("dense_head.") else 1.0
            std = np.sqrt(2.0 * shape[0] / n)
            if rule == "golden-weights-2" and n > LARGE:
                out[name] = uniform32(rng, n, np.sqrt(3.0) * std * scale).reshape(shape)
                continue
            v = rng.normal(0.0, std, n) * scale
        out[name] = v.astype(np.float32).reshape(shape)
    return out


def uniform32(rng: np.random.Generator, n: int, a: float) -> np.ndarray:
    """(n,) float32 U(-a, a): ``rng.random`` in float32, times float32(2 a), minus float32(a), in place."""
    v = rng.random(n, dtype=np.float32)
    v *= np.float32(2.0 * a)
    v -= np.float32(a)
    return v
