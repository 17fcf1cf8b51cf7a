"""The run's val set: simulated apart from the training set, every frame predicted and evaluated."""
import json

from harness import valset
from harness.core.kitti import read_frames_meta, read_image_set
from harness.run import PROFILES, RunConfig
from harness.stages import Stages

CFG = RunConfig("test", "tiny", train_frames=4, sotif_frames=21, epochs=1, workers=1, bootstrap=5, val_frames=4)


def test_the_val_set_is_every_frame_of_its_own_simulation(tmp_path, make_onnx):
    stages = Stages(tmp_path, progress=False)
    digest = valset.simulate(stages, CFG, tmp_path, ("training/label_2", "ImageSets", "meta"))
    data = tmp_path / "data" / "val"
    meta = read_frames_meta(data / "meta" / "frames.csv")
    assert digest and len(meta) == 4 and set(meta["split"]) == {"train", "val"}  # the generator's own split ...
    assert read_image_set(tmp_path / valset.FRAME_LIST) == meta["frame_id"].tolist()  # ... but all are val here
    assert json.loads((data / "meta" / "dataset.json").read_text())["config"]["seed"] == CFG.seed + valset.VAL_SEED_OFFSET
    (tmp_path / "models").mkdir()
    make_onnx(tmp_path / "models" / "m.onnx", two_stage=True)
    valset.predict_evaluate(stages, CFG, tmp_path, "m", "onnxruntime", 1)
    assert sorted(p.name for p in (tmp_path / "predictions_valset" / "m").glob("0*.txt")) == \
        [f"{i}.txt" for i in meta["frame_id"]]
    val = valset.val_summary(tmp_path, "m")
    assert val["n_frames"] == 4 and 0.0 <= val["3d_moderate"] <= 100.0
    assert val["data"] == "val: 4 held-out training-generator frames" and val["results"] == "results_valset/m.json"
    before = (tmp_path / ".stages" / "evaluate_valset_m.json").read_text()
    valset.predict_evaluate(stages, CFG, tmp_path, "m", "onnxruntime", 1)  # current: redone neither
    assert (tmp_path / ".stages" / "evaluate_valset_m.json").read_text() == before


def test_no_val_set_without_val_frames(tmp_path):
    from dataclasses import replace
    stages = Stages(tmp_path, progress=False)
    assert valset.simulate(stages, replace(CFG, val_frames=None), tmp_path, ("meta",)) is None
    assert valset.val_summary(tmp_path, "m") is None and not (tmp_path / "data").exists()
    assert PROFILES["default"].val_frames >= 300
