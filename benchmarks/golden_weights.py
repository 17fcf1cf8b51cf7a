"""The seeded rule that fills a reference checkpoint's tensors with random values (golden data of
``benchmarks/golden_published.py``; the tests rebuild the same file from the stored names, shapes
and seed). numpy's PCG64 in float64, cast to float32: the same values on every machine.

Per tensor, in the checkpoint's order: BatchNorm ``running_mean`` N(0, 0.1^2), ``running_var``,
and any other 1-D ``weight`` (BatchNorm's scale) U(0.5, 1.5); a 1-D ``bias`` N(0, 0.1^2) (the
class-logit bias of the head N(cls_bias, 0.1^2), so that a few anchors score above 0.1); a weight
of rank >= 2 N(0, 2 / fan_in) with fan_in = numel / shape[0], times ``head_scale`` in the dense head
(``dense_head.*``: PointPillars' bird's-eye map reaches ~80, so that its logits and box residuals stay
in range); integer counters 0.
"""
from __future__ import annotations

import numpy as np

RULE = "golden-weights-1"


def fill(names: list[str], shapes: list[tuple[int, ...]], seed: int, cls_bias: float,
         head_scale: float = 1.0) -> dict[str, np.ndarray]:
    """{name: array} in the checkpoint's layout; integer tensors (num_batches_tracked, global_step) int64."""
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
            v = rng.normal(0.0, np.sqrt(2.0 * shape[0] / n), n) * scale
        out[name] = v.astype(np.float32).reshape(shape)
    return out
