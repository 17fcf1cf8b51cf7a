import numpy as np
import pytest

from harness import evaluate as ev
from harness.core import kitti
from tests.harness.conftest import make_dataset
from tests.harness.test_evaluate_cli import copy_as_predictions


def test_cluster_resample_draws_whole_instances():
    rng = np.random.default_rng(0)
    frames = np.arange(12)
    clusters = np.repeat(["a#0", "a#1", "b#0", "b#1"], [2, 3, 3, 4])
    for _ in range(50):
        draw = ev.cluster_resample(frames, clusters, rng)
        for key in np.unique(clusters):
            members = frames[clusters == key]
            counts = [int((draw == f).sum()) for f in members]
            assert len(set(counts)) == 1  # an instance comes with all of its frames, each as often
        firsts = [frames[clusters == k][0] for k in np.unique(clusters)]
        assert sum(int((draw == f).sum()) for f in firsts) == 4  # as many instances drawn as there are


def test_bootstrap_ci_resamples_instances_not_frames(monkeypatch):
    seen = []

    def fake_precision_recall(es, metric, filt, thr, frames=None):
        seen.append(np.sort(np.asarray(frames)))
        return {"precision": np.full(41, float(len(frames)))}
    monkeypatch.setattr(ev, "precision_recall", fake_precision_recall)
    frames = np.arange(10)
    clusters = np.repeat(["x", "y"], [3, 7])
    lo, hi = ev.bootstrap_ci(None, frames, "3d", n=40, seed=1, clusters=clusters)
    # a draw holds 6, 10 or 14 frames (x x, x y, y y): a frame bootstrap always holds 10
    assert {len(f) for f in seen} == {6, 10, 14} and lo < hi
    assert all(len(set(np.bincount(f, minlength=10)[:3])) == 1 for f in seen)  # x's 3 frames come together
    seen.clear()
    ev.bootstrap_ci(None, frames, "3d", n=40, seed=1)
    assert {len(f) for f in seen} == {10}
    assert ev.ci_method(clusters, 40) == "bootstrap over instances (2 instances, 40 resamples)"
    assert ev.ci_method(None, 40) == "bootstrap over frames (40 resamples)"


def _instance_dataset(root):
    data = make_dataset(root, n_frames=12)
    meta = kitti.read_frames_meta(data / "meta" / "frames.csv")
    meta["instance"] = np.arange(12) // 6
    meta["instance_key"] = meta["weather"] + "#" + (np.arange(12) // 2 % 3).astype(str)
    meta["sc_ego_speed_kmh"] = np.linspace(80, 130, 12)
    meta["sc_slow_body"] = ["car", "van"] * 6
    kitti.write_frames_meta(data / "meta" / "frames.csv", meta)
    return data


def test_group_by_instance_columns(tmp_path):
    data = _instance_dataset(tmp_path / "d")
    pred = copy_as_predictions(data, tmp_path / "pred")
    res = ev.evaluate(data, pred, group_by=["weather", "sc_ego_speed_kmh", "sc_slow_body"],
                      meta=data / "meta" / "frames.csv", n_bootstrap=5)
    weather = res["groups_by"]["weather"]["rows"]
    assert all(r["ci_method"] == "bootstrap over instances (3 instances, 5 resamples)" for r in weather.values())
    speed = res["groups_by"]["sc_ego_speed_kmh"]["rows"]  # 12 values: four quantile bins of 3 frames
    assert list(speed) == ["[80, 92.5)", "[92.5, 105)", "[105, 118)", "[118, 130]"]
    assert all(r["n_frames"] == 3 for r in speed.values())
    assert set(res["groups_by"]["sc_slow_body"]["rows"]) == {"car", "van"}
    with pytest.raises(kitti.KittiError, match="--group-by 'sc_nope': no such condition column"):
        ev.evaluate(data, pred, group_by="sc_nope", meta=data / "meta" / "frames.csv")


def test_a_data_set_without_instances_keeps_its_groups_and_intervals(tmp_path, dataset):
    pred = copy_as_predictions(dataset, tmp_path / "pred")
    res = ev.evaluate(dataset, pred, group_by="weather", meta=dataset / "meta" / "frames.csv", n_bootstrap=7, seed=3)
    es_frames = {w: np.flatnonzero(np.array(["ClearNoon", "HardRainNight"] * 3) == w) for w in res["groups"]["rows"]}
    gt = ev.load_folder(ev.label_dir(dataset), ev.frame_ids(ev.label_dir(dataset)), with_score=False)
    dt = ev.load_folder(pred, ev.frame_ids(ev.label_dir(dataset)), with_score=True)
    es = ev.build_eval_set(gt, dt)
    for weather, row in res["groups"]["rows"].items():
        assert row["ci_method"] == "bootstrap over frames (7 resamples)"
        rng = np.random.default_rng(3)  # the frame bootstrap as it always drew
        frames = es_frames[weather]
        vals = [ev.ap_r40(ev.precision_recall(es, "3d", ev.ALL_DISTANCES, 0.7, rng.choice(frames, len(frames)))
                          ["precision"]) for _ in range(7)]
        assert row["headline_ci95"]["3d"] == [float(np.percentile(vals, 2.5)), float(np.percentile(vals, 97.5))]
