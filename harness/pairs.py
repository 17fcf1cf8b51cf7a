"""Paired comparisons of models: the difference of an AP between every two models with a 95 % interval
from a paired bootstrap over frames (or whole scenario instances) and training draws.

Pure algorithm functions (no file I/O; ``harness.pairs_run`` loads a run's predictions). A model is
given as a list of per-draw evaluation sets (``harness.eval_kitti.EvalSet``), every set built over the
same frames in the same order. Each bootstrap replicate first draws, for every model, one of its
training draws (with replacement), then resamples the resampling units (frames, or instances: all the
frames of an instance go together) with replacement; every model is scored on the same resampled
frames, so what the frames have in common cancels in the difference. The point estimate is the
difference of the models' means over their draws on all frames.
"""
from __future__ import annotations

from itertools import combinations
from typing import Callable, Sequence

import numpy as np

from harness.eval_kitti import DIFFICULTIES, ap_r40, precision_recall
from harness.evaluate import ALL_DISTANCES

PAIR_COLUMNS = ("model_a", "model_b", "metric", "data", "mean_diff", "ci_lo", "ci_hi", "apart", "unit",
                "n_units", "n_draws_a", "n_draws_b")


def val_ap(es, frames) -> float:
    """AP40 3D @0.7 with KITTI's moderate filter (%) of the frames ``frames`` (indices, repeats allowed)."""
    return ap_r40(precision_recall(es, "3d", DIFFICULTIES[1], 0.7, frames)["precision"])


def headline_ap(es, frames) -> float:
    """The SOTIF headline: AP40 3D @0.7 over all distances, filters off (%)."""
    return ap_r40(precision_recall(es, "3d", ALL_DISTANCES, 0.7, frames)["precision"])


def unit_frames(units: np.ndarray | None, n_frames: int) -> list[np.ndarray]:
    """The frame indices of each resampling unit: ``units`` (F,) labels each frame's instance; None: one
    unit per frame."""
    if units is None:
        return [np.array([i]) for i in range(n_frames)]
    units = np.asarray(units)
    return [np.flatnonzero(units == u) for u in dict.fromkeys(units.tolist())]


def bootstrap_scores(draw_sets: dict[str, Sequence], score: Callable, units: np.ndarray | None, n: int,
                     seed: int) -> tuple[dict[str, float], np.ndarray]:
    """Per model, the mean of ``score(set, all frames)`` over its draws, and the (n, M) replicate scores
    (models in ``draw_sets``' order): each replicate draws one training draw per model, then the units."""
    names = list(draw_sets)
    n_frames = draw_sets[names[0]][0].n_frames
    groups = unit_frames(units, n_frames)
    everything = np.arange(n_frames)
    means = {m: float(np.mean([score(es, everything) for es in draw_sets[m]])) for m in names}
    rng = np.random.default_rng(seed)
    reps = np.zeros((n, len(names)))
    for b in range(n):
        draws = [int(rng.integers(len(draw_sets[m]))) for m in names]
        picked = rng.integers(len(groups), size=len(groups))
        frames = np.concatenate([groups[u] for u in picked]) if len(groups) else everything
        reps[b] = [score(draw_sets[m][d], frames) for m, d in zip(names, draws)]
    return means, reps


def pair_rows(means: dict[str, float], reps: np.ndarray, n_draws: dict[str, int], metric: str, data: str,
              unit: str, n_units: int) -> list[dict]:
    """One row per pair of models (a before b in ``means``' order): mean difference a - b, the 2.5 and 97.5
    percentiles of the replicate differences, and whether that interval excludes 0 ("apart")."""
    names = list(means)
    rows = []
    for i, j in combinations(range(len(names)), 2):
        diff = reps[:, i] - reps[:, j]
        lo, hi = (float(np.percentile(diff, 2.5)), float(np.percentile(diff, 97.5))) if len(diff) else (0.0, 0.0)
        rows.append({"model_a": names[i], "model_b": names[j], "metric": metric, "data": data,
                     "mean_diff": means[names[i]] - means[names[j]], "ci_lo": lo, "ci_hi": hi,
                     "apart": bool(lo > 0 or hi < 0), "unit": unit, "n_units": n_units,
                     "n_draws_a": n_draws[names[i]], "n_draws_b": n_draws[names[j]]})
    return rows


def paired_comparison(draw_sets: dict[str, Sequence], score: Callable, metric: str, data: str,
                      units: np.ndarray | None = None, n: int = 200, seed: int = 0) -> list[dict]:
    """Every pair's difference of ``score`` with its paired-bootstrap 95 % interval (module docstring);
    ``units`` labels each frame's scenario instance (None: frames are resampled one by one)."""
    if n < 1:
        raise ValueError(f"bootstrap resamples must be at least 1, got {n}")
    means, reps = bootstrap_scores(draw_sets, score, units, n, seed)
    n_frames = next(iter(draw_sets.values()))[0].n_frames
    n_units = len(unit_frames(units, n_frames)) if units is not None else n_frames
    return pair_rows(means, reps, {m: len(s) for m, s in draw_sets.items()}, metric, data,
                     "instance" if units is not None else "frame", n_units)
