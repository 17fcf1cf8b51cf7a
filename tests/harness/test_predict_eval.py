"""The predict-then-evaluate stage pair of every data set of a run (SOTIF, sweep, val) keeps its stage names,
keys, outputs and calls: a run made before resumes with every stage skipped."""
import json
from dataclasses import replace

from harness import run as run_mod, valset
from harness.run import RunConfig
from harness.stages import Stages

CFG = RunConfig("test", "tiny", train_frames=6, sotif_frames=21, epochs=1, workers=1, bootstrap=5, val_frames=3)


class Recorder(Stages):
    """Stages that record each stage's name, raw key and outputs, and run it."""

    def __init__(self, root):
        super().__init__(root, progress=False)
        self.calls = []

    def run(self, name, key, fn, outputs=(), by_stat=False):
        self.calls.append((name, key, [str(o.relative_to(self.root)) for o in outputs]))
        return fn()

    def outputs_digest(self, name):
        return f"digest of {name}"


def _fakes(monkeypatch, root):
    calls = []
    rel = lambda kw: {k: str(v.relative_to(root)) if hasattr(v, "relative_to") else v for k, v in kw.items()}

    def predict(onnx, data, out, **kw):
        calls.append(("predict", str(onnx.relative_to(root)), str(data.relative_to(root)),
                      str(out.relative_to(root)), rel(kw)))
        out.mkdir(parents=True, exist_ok=True)
        (out / "predict.json").write_text(json.dumps({"n_frames": 1}))
        return {"n_frames": 1}

    def evaluate(data, pred, **kw):
        calls.append(("evaluate", str(data.relative_to(root)), str(pred.relative_to(root)), rel(kw)))
        return {}
    monkeypatch.setattr("harness.infer.predict", predict)
    monkeypatch.setattr("harness.evaluate.evaluate", evaluate)
    monkeypatch.setattr("harness.evaluate.write_results", lambda path, res: calls.append(("write", path.name)))
    return calls


def test_the_stage_pairs_keep_their_names_keys_and_calls(tmp_path, monkeypatch):
    calls = _fakes(monkeypatch, tmp_path)
    for rel in ("data/sotif/ImageSets", "data/val/meta", "models"):
        (tmp_path / rel).mkdir(parents=True)
    (tmp_path / "data/sotif/ImageSets/val.txt").write_text("000001\n")
    (tmp_path / "data/val/meta/dataset.json").write_text("{}")
    (tmp_path / valset.FRAME_LIST).write_text("000000\n")
    (tmp_path / "models/m.onnx").write_bytes(b"onnx")
    onnx = run_mod.file_digest(tmp_path / "models/m.onnx")
    val = run_mod.file_digest(tmp_path / "data/val/meta/dataset.json")
    stages = Recorder(tmp_path)
    assert run_mod._predict_eval(stages, CFG, tmp_path, "m", "sotif-hash", "onnxruntime", 1, "sweep-hash") == \
        {"n_frames": 1}
    valset.predict_evaluate(stages, CFG, tmp_path, "m", "onnxruntime", 1)
    key = {"onnx": onnx, "runtime": "onnxruntime"}
    sotif, sweep, vkey = {**key, "data": "sotif-hash"}, {**key, "data": "sweep-hash"}, {**key, "data": val}
    assert sorted(stages.calls) == sorted([
        ("predict_m", sotif, ["predictions/m"]),
        ("predict_val_m", sotif, ["predictions_val/m"]),
        ("evaluate_m", {**sotif, "bootstrap": 5, "evaluator": _evaluator(), "predictions": "digest of predict_m"},
         ["results/m.json"]),
        ("predict_sweep_m", sweep, ["predictions_sweep/m"]),
        ("evaluate_sweep_m", {**sweep, "bootstrap": 5, "evaluator": _evaluator(),
                              "predictions": "digest of predict_sweep_m"}, ["results/m.sweep.json"]),
        ("predict_valset_m", vkey, ["predictions_valset/m"]),  # the val set's evaluation is keyed without bootstrap
        ("evaluate_valset_m", {**vkey, "evaluator": _evaluator(), "predictions": "digest of predict_valset_m"},
         ["results_valset/m.json"])], key=str)
    groups = ["weather", "time_of_day", "precipitation_class"]
    sweep_groups = ["sweep_axis", "rain_rate_mmh", "fog_mor_m", "road_water", "precipitation_class"]
    pred = {"runtime": "onnxruntime", "threads": 1}
    assert sorted(calls, key=str) == sorted([
        ("predict", "models/m.onnx", "data/sotif", "predictions/m", {**pred, "split": "test", "progress": False}),
        ("predict", "models/m.onnx", "data/sotif", "predictions_val/m", {**pred, "split": "val", "progress": False}),
        ("evaluate", "data/sotif", "predictions/m", {"split": "data/sotif/ImageSets/test.txt", "group_by": groups,
                                                     "meta": "data/sotif/meta/frames.csv", "n_bootstrap": 5,
                                                     "seed": 0}),
        ("write", "m.json"),
        ("predict", "models/m.onnx", "data/sweep", "predictions_sweep/m", {**pred, "split": "test",
                                                                           "progress": False}),
        ("evaluate", "data/sweep", "predictions_sweep/m", {"split": "data/sweep/ImageSets/test.txt",
                                                           "group_by": sweep_groups,
                                                           "meta": "data/sweep/meta/frames.csv", "n_bootstrap": 5,
                                                           "seed": 0}),
        ("write", "m.sweep.json"),
        ("predict", "models/m.onnx", "data/val", "predictions_valset/m", {**pred, "split": "data/val_frames.txt",
                                                                          "progress": False}),
        ("evaluate", "data/val", "predictions_valset/m", {"split": "data/val_frames.txt", "n_bootstrap": 5,
                                                          "seed": 0}),
        ("write", "m.json")], key=str)


def _evaluator():
    from harness.evaluate import EVALUATOR_VERSION
    return EVALUATOR_VERSION


def test_no_val_split_no_val_predictions(tmp_path, monkeypatch):
    _fakes(monkeypatch, tmp_path)
    (tmp_path / "data/sotif/ImageSets").mkdir(parents=True)
    (tmp_path / "data/sotif/ImageSets/val.txt").write_text("")
    stages = Recorder(tmp_path)
    run_mod._predict_eval(stages, replace(CFG, val_frames=None), tmp_path, "m", "h", "onnxruntime")
    assert [c[0] for c in stages.calls] == ["predict_m", "evaluate_m"]
    valset.predict_evaluate(stages, replace(CFG, val_frames=None), tmp_path, "m", "onnxruntime", None)
    assert len(stages.calls) == 2
