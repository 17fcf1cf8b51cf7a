import pytest
import torch

from models import zoo
from models.pointpillars import PointPillars


def test_build_by_name_and_profiles():
    model = zoo.build("pointpillars", "tiny")
    assert isinstance(model, PointPillars) and model.architecture == "pointpillars"
    for name in ("pointpillars", "second", "dv_second"):
        assert set(zoo._module(name).CONFIGS) == {"tiny", "compact", "kitti"}
        assert name in zoo.available()
    assert set(zoo.available()) <= set(zoo.MODEL_NAMES)


def test_unknown_names_are_clear_errors():
    with pytest.raises(ValueError, match="unknown model 'yolo'"):
        zoo.build("yolo")
    with pytest.raises(ValueError, match="unknown profile 'huge'"):
        zoo.build("second", "huge")


def test_models_are_different_networks():
    counts = {n: zoo.count_parameters(zoo.build(n, "compact")) for n in ("pointpillars", "second")}
    assert counts["pointpillars"] != counts["second"]
    assert zoo.build("dv_second", "tiny").voxelize.__func__ is not zoo.build("second", "tiny").voxelize.__func__


def test_load_checkpoint_roundtrip_and_errors(tmp_path):
    model = zoo.build("second", "tiny")
    torch.save({"model": "second", "profile": "tiny", "state_dict": model.state_dict(), "epoch": 3,
                "optimizer": {}}, tmp_path / "c.pt")
    loaded, meta = zoo.load_checkpoint(tmp_path / "c.pt")
    assert meta == {"model": "second", "profile": "tiny", "epoch": 3} and not loaded.training
    for k, v in model.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k])
    with pytest.raises(zoo.CheckpointError, match="not found"):
        zoo.load_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(zoo.CheckpointError, match="bad.pt"):
        zoo.load_checkpoint(tmp_path / "bad.pt")
    torch.save({"model": "pointpillars", "profile": "tiny", "state_dict": model.state_dict()}, tmp_path / "x.pt")
    with pytest.raises(zoo.CheckpointError, match="do not fit"):
        zoo.load_checkpoint(tmp_path / "x.pt")
