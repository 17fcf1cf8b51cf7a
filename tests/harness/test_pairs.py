"""Paired bootstrap of the difference between two models: degenerate cases and a numpy reference."""
from dataclasses import dataclass

import numpy as np
import pytest

from harness.core.kitti import Labels
from harness.eval_kitti import build_eval_set
from harness.pairs import headline_ap, paired_comparison, unit_frames, val_ap


def cars(xs, score=None):
    """Cars at lateral offsets ``xs`` 20 m ahead, 60 px tall (KITTI easy/moderate), unoccluded."""
    k = len(xs)
    if not k:
        return Labels.empty(with_score=score is not None)
    bbox = np.array([[100 + 150 * i, 150, 200 + 150 * i, 210] for i in range(k)], float)
    return Labels(name=np.array(["Car"] * k, dtype=object), truncated=np.zeros(k), occluded=np.zeros(k, int),
                  alpha=np.zeros(k), bbox=bbox, dimensions=np.tile([1.5, 1.6, 3.9], (k, 1)),
                  location=np.array([[x, 1.6, 20.0] for x in xs]), rotation_y=np.zeros(k),
                  score=None if score is None else np.asarray(score, float))


def frames(n=60, seed=0):
    """Ground truth of ``n`` frames with 1-3 cars each, and three detection sets: every car right,
    nothing, every other frame right."""
    rng = np.random.default_rng(seed)
    gt = [cars(list(rng.uniform(-8, 8, rng.integers(1, 4)))) for _ in range(n)]
    right = [cars(list(g.location[:, 0]), score=rng.uniform(0.5, 1, len(g))) for g in gt]
    none = [cars([], score=[]) for _ in gt]
    half = [r if i % 2 else e for i, (r, e) in enumerate(zip(right, none))]
    return gt, right, none, half


@pytest.mark.parametrize("score", [val_ap, headline_ap])
def test_identical_models_are_not_apart(score):
    gt, _, _, half = frames()
    es = build_eval_set(gt, half)
    (row,) = paired_comparison({"a": [es], "b": [build_eval_set(gt, half)]}, score, "m", "d", n=50)
    assert row["mean_diff"] == 0 and row["ci_lo"] <= 0 <= row["ci_hi"] and not row["apart"]
    assert (row["unit"], row["n_units"], row["n_draws_a"]) == ("frame", 60, 1)


@pytest.mark.parametrize("score", [val_ap, headline_ap])
def test_every_box_right_against_none_is_apart(score):
    gt, right, none, _ = frames()
    rows = paired_comparison({"right": [build_eval_set(gt, right)], "none": [build_eval_set(gt, none)]},
                             score, "m", "d", n=50)
    assert rows[0]["model_a"] == "right" and rows[0]["mean_diff"] == pytest.approx(100.0)
    assert rows[0]["ci_lo"] > 90 and rows[0]["apart"]


def test_draws_are_resampled():
    # a model whose two draws are perfect and empty is on average 50 below a perfect one, but a replicate
    # that picks its perfect draw finds no difference: not apart
    gt, right, none, _ = frames()
    row, = paired_comparison({"a": [build_eval_set(gt, right), build_eval_set(gt, none)],
                              "b": [build_eval_set(gt, right)]}, val_ap, "m", "d", n=100)
    assert row["mean_diff"] == pytest.approx(-50.0) and row["ci_hi"] == pytest.approx(0.0)
    assert row["ci_lo"] == pytest.approx(-100.0) and not row["apart"] and row["n_draws_a"] == 2


@dataclass
class Scores:
    """A stand-in evaluation set: one number per frame; its score of a resample is their mean."""

    values: np.ndarray

    @property
    def n_frames(self) -> int:
        return len(self.values)


def mean_score(s: Scores, idx) -> float:
    return float(s.values[idx].mean())


def reference(models: dict, units, n: int, seed: int) -> list[tuple]:
    """The paired bootstrap written out in numpy: per replicate a draw per model, then units."""
    labels = np.arange(len(models["a"][0].values)) if units is None else np.asarray(units)
    uniq = list(dict.fromkeys(labels.tolist()))
    rng = np.random.default_rng(seed)
    reps = {m: [] for m in models}
    for _ in range(n):
        d = {m: rng.integers(len(ds)) for m, ds in models.items()}
        take = rng.integers(len(uniq), size=len(uniq))
        idx = np.concatenate([np.nonzero(labels == uniq[u])[0] for u in take])
        for m in models:
            reps[m].append(models[m][d[m]].values[idx].mean())
    out = []
    names = list(models)
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            diff = np.array(reps[names[i]]) - np.array(reps[names[j]])
            mean = np.mean([s.values.mean() for s in models[names[i]]]) - np.mean([s.values.mean() for s in models[names[j]]])
            out.append((mean, np.percentile(diff, 2.5), np.percentile(diff, 97.5)))
    return out


@pytest.mark.parametrize("units", [None, [0, 0, 1, 1, 1, 2, 3]])
def test_bootstrap_follows_the_numpy_reference(units):
    rng = np.random.default_rng(3)
    models = {"a": [Scores(rng.normal(size=7)), Scores(rng.normal(size=7))], "b": [Scores(rng.normal(size=7))],
              "c": [Scores(rng.normal(size=7)) for _ in range(3)]}
    rows = paired_comparison(models, mean_score, "m", "d", units=units, n=300, seed=5)
    ref = reference(models, units, 300, 5)
    assert [(r["model_a"], r["model_b"]) for r in rows] == [("a", "b"), ("a", "c"), ("b", "c")]
    np.testing.assert_allclose([(r["mean_diff"], r["ci_lo"], r["ci_hi"]) for r in rows], ref, atol=1e-12)
    assert all(r["apart"] == (r["ci_lo"] > 0 or r["ci_hi"] < 0) for r in rows)
    assert rows[0]["n_units"] == (7 if units is None else 4)
    assert rows[0]["unit"] == ("frame" if units is None else "instance")


def test_an_instance_moves_whole():
    groups = unit_frames(np.array(["x", "y", "x", "z"]), 4)
    assert [g.tolist() for g in groups] == [[0, 2], [1], [3]]
    # a frame difference that is constant within instances and differs in sign between them: an instance
    # resample only ever holds whole instances, so every replicate's mean is a weighted mean of +1 and -1
    a = Scores(np.array([1.0, 1.0, -1.0, -1.0]))
    rows = paired_comparison({"a": [a], "b": [Scores(np.zeros(4))]}, mean_score, "m", "d", units=[0, 0, 1, 1], n=200)
    assert rows[0]["ci_lo"] == pytest.approx(-1.0) and rows[0]["ci_hi"] == pytest.approx(1.0)


def test_no_resamples_is_refused():
    with pytest.raises(ValueError, match="at least 1"):
        paired_comparison({"a": [Scores(np.zeros(2))], "b": [Scores(np.zeros(2))]}, mean_score, "m", "d", n=0)
