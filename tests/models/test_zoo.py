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


def test_weights_with_nan_or_inf_and_configs_that_build_no_network_are_refused(tmp_path):
    import dataclasses
    state = zoo.build("pointpillars", "tiny").state_dict()
    name = next(n for n, t in state.items() if t.is_floating_point() and t.numel() > 1)
    bad = {**state, name: state[name].clone().index_fill_(0, torch.tensor([0]), float("nan"))}
    torch.save({"model": "pointpillars", "profile": "tiny", "state_dict": bad}, tmp_path / "nan.pt")
    message = rf"nan\.pt: 1 of its {len(state)} tensors hold NaN or inf \(first: {name}\); the training that wrote it diverged"
    with pytest.raises(zoo.CheckpointError, match=message):
        zoo.load_checkpoint(tmp_path / "nan.pt")
    with pytest.raises(zoo.CheckpointError, match=message):  # nor does it start another training
        zoo.warm_start(zoo.build("pointpillars", "tiny"), "pointpillars", tmp_path / "nan.pt")
    var = next(n for n in state if n.endswith("running_var"))
    torch.save({"model": "pointpillars", "profile": "tiny",
                "state_dict": {**state, var: state[var].clone().fill_(-5.0)}}, tmp_path / "var.pt")
    with pytest.raises(zoo.CheckpointError, match=rf"var\.pt: the BatchNorm variance {var} holds negative values"):
        zoo.load_checkpoint(tmp_path / "var.pt")
    cfg = dataclasses.asdict(zoo.config("pointpillars", "tiny")) | {"voxel_size": (-0.5, 0.5, 4.0)}
    torch.save({"model": "pointpillars", "profile": "tiny", "config": cfg, "state_dict": state}, tmp_path / "cfg.pt")
    with pytest.raises(zoo.CheckpointError, match=r"cfg\.pt: its pointpillars/tiny config does not build the network"):
        zoo.load_checkpoint(tmp_path / "cfg.pt")


@pytest.mark.parametrize("name", zoo.MODEL_NAMES)
def test_config_from_dict_rebuilds_every_profile_exactly(name, tmp_path):
    import dataclasses
    for profile, cfg in zoo._module(name).CONFIGS.items():
        saved = dataclasses.asdict(cfg)
        assert zoo.config_from_dict(cfg, saved) == cfg, profile
        # through torch.save / load (weights_only), as a checkpoint stores it
        torch.save({"config": saved}, tmp_path / "c.pt")
        stored = torch.load(tmp_path / "c.pt", weights_only=True)["config"]
        assert zoo.config_from_dict(cfg, stored) == cfg and zoo.config_changes(cfg, cfg) == [], profile
    assert zoo.detector_class(name).architecture == name


def test_load_checkpoint_builds_the_config_it_was_trained_with(tmp_path):
    import dataclasses
    from models.point_rcnn import CONFIGS
    tiny = CONFIGS["tiny"]
    trained = dataclasses.replace(tiny, pre_nms=tiny.pre_nms * 2, sa_npoints=(48, 12),
                                  targets=dataclasses.replace(tiny.targets, score_type="roi_iou"))
    model = zoo.detector_class("point_rcnn")(trained)
    torch.save({"model": "point_rcnn", "profile": "tiny", "config": dataclasses.asdict(trained),
                "state_dict": model.state_dict()}, tmp_path / "p.pt")
    loaded, meta = zoo.load_checkpoint(tmp_path / "p.pt")
    # the weights' shapes fit either config: only the saved one is the network they were trained in
    assert loaded.cfg == trained and loaded.cfg != tiny
    assert sorted(meta["config_changed"]) == ["pre_nms", "sa_npoints", "targets.score_type"]
    torch.save({"model": "point_rcnn", "profile": "tiny", "config": dataclasses.asdict(tiny),
                "state_dict": zoo.build("point_rcnn", "tiny").state_dict()}, tmp_path / "same.pt")
    loaded, meta = zoo.load_checkpoint(tmp_path / "same.pt")
    assert loaded.cfg == tiny and "config_changed" not in meta
    bad = dataclasses.asdict(tiny) | {"warp_drive": 9}
    torch.save({"model": "point_rcnn", "profile": "tiny", "config": bad,
                "state_dict": model.state_dict()}, tmp_path / "bad.pt")
    with pytest.raises(zoo.CheckpointError, match=r"bad\.pt: .*warp_drive"):
        zoo.load_checkpoint(tmp_path / "bad.pt")
    nested = dataclasses.asdict(tiny)
    nested["targets"]["flux"] = 1
    torch.save({"model": "point_rcnn", "profile": "tiny", "config": nested,
                "state_dict": model.state_dict()}, tmp_path / "nested.pt")
    with pytest.raises(zoo.CheckpointError, match=r"targets\.flux"):
        zoo.load_checkpoint(tmp_path / "nested.pt")
