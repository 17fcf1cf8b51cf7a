"""A run's paired comparisons: its prediction folders and draws, instances, and the cache."""
import json

import pandas as pd
import pytest

from harness import pairs_run
from harness.core import kitti
from harness.core.files import atomic_write_text
from tests.harness.test_report import make_run


@pytest.fixture
def run_dir(tmp_path):
    return make_run(tmp_path / "run")


def summary(run_dir):
    return json.loads((run_dir / "results.json").read_text())


def test_pairs_of_a_run_and_their_cache(run_dir, monkeypatch):
    got = pairs_run.load_or_compute(run_dir, summary(run_dir))
    assert [(r["model_a"], r["model_b"], r["metric"]) for r in got["rows"]] == \
        [("alpha", "beta", "val_ap3d_moderate"), ("alpha", "beta", "headline_ap3d")]
    assert got["rows"][1]["data"] == "SOTIF test: 9 frames" and got["rows"][1]["unit"] == "frame"
    assert [(p["model"], p["metric"]) for p in got["proposals"]] == [("beta", "val_ap3d_moderate"),
                                                                      ("beta", "headline_ap3d")]
    monkeypatch.setattr(pairs_run, "compute", lambda *a: pytest.fail("the cache was not used"))
    assert pairs_run.load_or_compute(run_dir, summary(run_dir)) == got
    monkeypatch.undo()
    # a changed prediction file computes again
    path = run_dir / "predictions" / "beta" / "000001.txt"
    path.write_text("")
    again = pairs_run.load_or_compute(run_dir, summary(run_dir))
    assert again["key"] != got["key"] and again["rows"][1]["mean_diff"] != got["rows"][1]["mean_diff"]


def test_instances_are_the_unit_when_the_data_set_has_them(run_dir):
    meta_path = run_dir / "data" / "sotif" / "meta" / "frames.csv"
    meta = kitti.read_frames_meta(meta_path)
    meta["instance_key"] = [f"i{int(f) // 4}" for f in meta["frame_id"]]  # one instance per weather
    kitti.write_frames_meta(meta_path, meta)
    rows = pairs_run.load_or_compute(run_dir, summary(run_dir))["rows"]
    assert (rows[1]["unit"], rows[1]["n_units"]) == ("instance", 3)


def test_draws_of_a_run_with_seeds(run_dir):
    import shutil
    doc = summary(run_dir)
    for name in ("alpha", "beta"):
        for folder in ("predictions", "predictions_val"):
            shutil.copytree(run_dir / folder / name, run_dir / folder / f"{name}.seed1")
    doc["draws"] = {n: [{"tag": n, "seed": 0}, {"tag": f"{n}.seed1", "seed": 1}] for n in ("alpha", "beta")}
    rows = pairs_run.load_or_compute(run_dir, doc)["rows"]
    assert all((r["n_draws_a"], r["n_draws_b"]) == (2, 2) for r in rows)


def test_a_copy_without_predictions_keeps_the_cached_rows(run_dir):
    import shutil
    got = pairs_run.load_or_compute(run_dir, summary(run_dir))
    shutil.rmtree(run_dir / "predictions")
    assert pairs_run.load_or_compute(run_dir, summary(run_dir)) == got
    tables = pairs_run.pair_tables(run_dir, summary(run_dir))
    assert isinstance(tables["pairs"], pd.DataFrame) and len(tables["pairs"]) == 2


def test_val_ap_is_compared_on_the_val_set_when_the_run_has_one(run_dir):
    import shutil
    shutil.copytree(run_dir / "data" / "sotif", run_dir / "data" / "val")
    ids = sorted(p.stem for p in (run_dir / "data" / "val" / "training" / "label_2").glob("*.txt"))
    atomic_write_text(run_dir / "data" / "val_frames.txt", "".join(f"{i}\n" for i in ids))
    for name in ("alpha", "beta"):
        for folder in ("predictions", "predictions_val"):
            shutil.copytree(run_dir / folder / name, run_dir / "predictions_valset" / name, dirs_exist_ok=True)
    rows = pairs_run.load_or_compute(run_dir, summary(run_dir))["rows"]
    assert (rows[0]["metric"], rows[0]["data"], rows[0]["n_units"]) == \
        ("val_ap3d_moderate", "val: 12 held-out training-generator frames", 12)
