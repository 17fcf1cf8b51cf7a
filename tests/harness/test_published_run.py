"""run --checkpoints: imported models evaluated beside trained ones, and bad input refused before any work."""
import json

import pandas as pd
import pytest
import torch

from harness import published_run
from harness.cli import main
from harness.import_weights import import_checkpoint
from harness.run import RunConfig, run
from tests.harness import published_layouts as layouts
from tests.harness.test_import_weights import openpcdet_file, random_state

TAG = "pointpillars_openpcdet"
SMALL = RunConfig("test", "tiny", train_frames=6, sotif_frames=21, epochs=1, workers=1, bootstrap=5, runtime_frames=1,
                  jobs=1, val_frames=3)


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    """A folder holding one imported checkpoint: OpenPCDet PointPillars of random weights in its published layout."""
    root = tmp_path_factory.mktemp("published")
    openpcdet_file(root / "pointpillar.pth", random_state(layouts.openpcdet_pointpillars()))
    (root / "imported").mkdir()
    import_checkpoint(root / "pointpillar.pth", "openpcdet", "pointpillars", root / "imported" / "pp.pt")
    return root / "imported"


def _run(out, *args):
    return main(["--quiet", "run", "--profile", "quick", "--out", str(out), *map(str, args)])


def test_bad_checkpoints_exit_2_naming_the_file_before_any_work(imported, tmp_path, capsys):
    out = tmp_path / "run"
    ckpt = imported / "pp.pt"
    (tmp_path / "empty").mkdir()
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    trained = torch.load(ckpt, weights_only=True)
    torch.save({k: v for k, v in trained.items() if k != "published"}, tmp_path / "trained.pt")
    torch.save({**trained, "published": {"source": "openpcdet"}}, tmp_path / "partial.pt")
    (tmp_path / "two").mkdir()
    for name in ("a.pt", "b.pt"):
        (tmp_path / "two" / name).write_bytes(ckpt.read_bytes())
    cases = [(tmp_path / "nothing", "no such file or folder"), (tmp_path / "empty", "holds no .pt file"),
             (tmp_path / "junk.pt", "not a checkpoint"), (tmp_path / "trained.pt", "without published provenance"),
             (tmp_path / "partial.pt", "not what `sotif-bench import` writes"),
             (tmp_path / "two", f"its model tag {TAG} is also")]
    for path, problem in cases:
        assert _run(out, "--models", "none", "--checkpoints", path) == 2, path
        err = capsys.readouterr().err
        assert problem in err and (path.name in err), err
        assert not out.exists()  # refused before the run folder is made
    assert _run(out, "--models", "none") == 2 and "--models none: no model to run" in capsys.readouterr().err
    assert not out.exists()


def test_the_published_models_are_added_to_the_selected_ones(imported):
    cfg, names = published_run.add(SMALL, ["pointpillars"], imported)
    assert names == ["pointpillars", TAG] and cfg.published == ((TAG, str((imported / "pp.pt").resolve())),)
    assert published_run.trained(cfg, names) == ["pointpillars"]
    assert published_run.draws(cfg, TAG) == 1 and published_run.draws(cfg, "pointpillars") == cfg.seeds
    assert published_run.add(SMALL, ["second"], None) == (SMALL, ["second"])


def test_an_imported_model_runs_beside_none_trained(imported, tmp_path, monkeypatch):
    """The run's plumbing with the kitti export stubbed (a kitti export takes minutes): the stub writes a
    contract-conforming detector carrying the checkpoint's provenance, as the real export does; the copy,
    prediction, evaluation, runtime probe, results.json and report are the real ones."""
    from models.zoo import read_checkpoint
    from tests.harness.conftest import centroid_detector
    exported = []

    def export(ckpt, out, expected_model=None, say=None):
        exported.append((ckpt.relative_to(tmp_path).as_posix(), expected_model))
        meta = {"sotif.contract": "1", "sotif.architecture": "pointpillars", "sotif.classes": "Car",
                "sotif.point_cloud_range": "[0, -39.68, -3, 69.12, 39.68, 1]",
                "sotif.published": json.dumps(read_checkpoint(ckpt)["published"])}
        return centroid_detector(out, metadata=meta)
    monkeypatch.setattr("models.export.export_checkpoint", export)
    out = run(models=[], out=tmp_path / "run", progress=False, config=SMALL, checkpoints=imported)
    assert exported == [(f"run/models/{TAG}/checkpoint.pt", "pointpillars")]
    assert (out / "models" / TAG / "checkpoint.pt").read_bytes() == (imported / "pp.pt").read_bytes()
    assert not (out / "data" / "train").exists()  # no trained model: no training set
    summary = json.loads((out / "results.json").read_text())
    entry = summary["models"][TAG]
    assert list(summary["models"]) == [TAG] and entry["train"] is None
    assert entry["published"]["config"] == "OpenPCDet tools/cfgs/kitti_models/pointpillar.yaml"
    assert entry["published"]["file"] == "pointpillar.pth" and summary["data"]["n_train_frames"] is None
    assert summary["config"]["published"] == [[TAG, str((imported / "pp.pt").resolve())]]
    stages = {p.stem for p in (out / ".stages").glob("*.json")}
    assert {f"{s}_{TAG}" for s in ("import", "export", "predict", "evaluate", "predict_valset", "evaluate_valset",
                                    "runtime")} <= stages and not any(s.startswith("train") for s in stages)
    overview = pd.read_csv(out / "tables" / "overview.csv")
    assert overview[["model", "weights"]].values.tolist() == [[TAG, "published"]]
    report = (out / "report.md").read_text()
    assert f"Published weights, imported and not trained in this run (`run --checkpoints`): {TAG}: OpenPCDet " \
           "tools/cfgs/kitti_models/pointpillar.yaml, file pointpillar.pth" in report
    assert "| published |" in report
    before = {p.name: p.read_text() for p in (out / ".stages").glob("*.json")}
    run(models=[], out=out, progress=False, config=SMALL, checkpoints=imported)  # resumed: every stage skipped
    assert {p.name: p.read_text() for p in (out / ".stages").glob("*.json")} == before
