import collections

import pytest
import torch

from harness.cli import main
from harness.import_weights import PublishedFileError, import_checkpoint
from models import zoo
from tests.harness import published_layouts as layouts


def random_state(shapes: dict, seed: int = 0) -> collections.OrderedDict:
    gen = torch.Generator().manual_seed(seed)
    out = collections.OrderedDict()
    for name, shape in shapes.items():
        if name.endswith("num_batches_tracked") or name == "global_step":
            out[name] = torch.randint(0, 1000, shape, generator=gen)
        elif name.endswith("running_var"):
            out[name] = torch.rand(shape, generator=gen) + 0.5
        else:
            out[name] = torch.randn(shape, generator=gen)
    return out


def openpcdet_file(path, state):
    torch.save({"epoch": 80, "it": 0, "model_state": state, "optimizer_state": {}, "version": "pcdet+0.6.0"},
               path, _use_new_zipfile_serialization=False)  # OpenPCDet's legacy save


def mmdet3d_file(path, state, v2: bool, classes=("Pedestrian", "Cyclist", "Car")):
    state._metadata = collections.OrderedDict()
    for name in state:
        if name.startswith("middle_encoder") and name.endswith(".0.weight"):
            state._metadata[name[:-len(".weight")]] = {"version": 2 if v2 else 1}
    torch.save({"meta": {"epoch": 80, "dataset_meta": {"classes": list(classes)}}, "state_dict": state}, path)


def test_pointpillars_imports_every_tensor(tmp_path):
    state = random_state(layouts.openpcdet_pointpillars())
    openpcdet_file(tmp_path / "pp.pth", state)
    info = import_checkpoint(tmp_path / "pp.pth", "openpcdet", "pointpillars", tmp_path / "pp.pt")
    assert info["classes"] == ["Car", "Pedestrian", "Cyclist"]
    model, meta = zoo.load_checkpoint(tmp_path / "pp.pt")
    sd = model.state_dict()
    assert meta["published"]["source"] == "openpcdet"
    torch.testing.assert_close(sd["vfe.linear.weight"], state["vfe.pfn_layers.0.linear.weight"])
    torch.testing.assert_close(sd["backbone2d.blocks.1.3.weight"], state["backbone_2d.blocks.1.4.weight"])  # ZeroPad2d
    torch.testing.assert_close(sd["backbone2d.ups.2.1.running_var"], state["backbone_2d.deblocks.2.1.running_var"])
    torch.testing.assert_close(sd["head.conv_dir.bias"], state["dense_head.conv_dir_cls.bias"])


def _check_sparse(ours, ref, v2: bool):
    """ours (K, in, out), z slowest, against a spconv weight element by element."""
    k, c_in, c_out = ours.shape
    kernel = ref.shape[1:4] if v2 else ref.shape[:3]
    gen = torch.Generator().manual_seed(1)
    for _ in range(50):
        kd, kh, kw = (int(torch.randint(0, n, (1,), generator=gen)) for n in kernel)
        i, o = int(torch.randint(0, c_in, (1,), generator=gen)), int(torch.randint(0, c_out, (1,), generator=gen))
        want = ref[o, kd, kh, kw, i] if v2 else ref[kd, kh, kw, i, o]
        assert ours[(kd * kernel[1] + kh) * kernel[2] + kw, i, o] == want


@pytest.mark.parametrize("v2", [False, True])
def test_second_sparse_layout_from_shapes(tmp_path, v2):
    state = random_state(layouts.openpcdet_second(v2))
    openpcdet_file(tmp_path / "s.pth", state)
    import_checkpoint(tmp_path / "s.pth", "openpcdet", "second", tmp_path / "s.pt")
    sd = zoo.load_checkpoint(tmp_path / "s.pt")[0].state_dict()
    _check_sparse(sd["backbone3d.stem.1.0.weight"], state["backbone_3d.conv1.0.0.weight"], v2)  # 16 -> 16
    _check_sparse(sd["backbone3d.stages.2.2.0.weight"], state["backbone_3d.conv4.2.0.weight"], v2)
    _check_sparse(sd["backbone3d.out.0.weight"], state["backbone_3d.conv_out.0.weight"], v2)
    torch.testing.assert_close(sd["backbone3d.stages.0.1.1.norm.running_mean"],
                               state["backbone_3d.conv2.1.1.running_mean"])


@pytest.mark.parametrize("v2", [False, True])
def test_dv_second_layout_from_metadata(tmp_path, v2):
    state = random_state(layouts.mmdet3d_dv_second(v2))
    mmdet3d_file(tmp_path / "d.pth", state, v2)
    import_checkpoint(tmp_path / "d.pth", "mmdet3d", "dv_second", tmp_path / "d.pt")
    sd = zoo.load_checkpoint(tmp_path / "d.pt")[0].state_dict()
    p = "middle_encoder.encoder_layers.encoder_layer"
    _check_sparse(sd["backbone3d.stem.1.0.weight"], state[f"{p}1.0.0.weight"], v2)
    _check_sparse(sd["backbone3d.stages.1.0.0.weight"], state[f"{p}3.0.0.weight"], v2)
    torch.testing.assert_close(sd["head.conv_box.weight"], state["bbox_head.conv_reg.weight"])
    torch.testing.assert_close(sd["backbone2d.blocks.0.3.weight"], state["backbone.blocks.0.3.weight"])


def test_16_to_16_layout_read_from_metadata_not_shape(tmp_path):
    """A file saved by spconv 1.x whose metadata says version 2 is read as 2.x: the 16 -> 16 conv's
    shape fits both, the metadata decides (and the 4 -> 16 one then misfits)."""
    state = random_state(layouts.mmdet3d_dv_second(False))
    mmdet3d_file(tmp_path / "d.pth", state, v2=True)
    with pytest.raises(PublishedFileError, match="conv_input.0.weight"):
        import_checkpoint(tmp_path / "d.pth", "mmdet3d", "dv_second", tmp_path / "d.pt")
    assert not (tmp_path / "d.pt").exists()


def _run(*args):
    return main(["import", *map(str, args)])


def test_wrong_files_exit_2_listing_the_tensors(tmp_path, capsys):
    full = layouts.openpcdet_second(True)
    cases = {"missing": {k: v for k, v in full.items() if k != "dense_head.conv_box.bias"},
             "extra": {**full, "roi_head.shared_fc.0.weight": (256, 512)},
             "shape": {**full, "backbone_2d.blocks.0.1.weight": (128, 255, 3, 3)}}
    expect = {"missing": "head.conv_box.bias", "extra": "roi_head.shared_fc.0.weight",
              "shape": "backbone_2d.blocks.0.1.weight"}
    for what, shapes in cases.items():
        openpcdet_file(tmp_path / f"{what}.pth", random_state(shapes))
        assert _run("--from", "openpcdet", "--model", "second", "--checkpoint", tmp_path / f"{what}.pth",
                    "--out", tmp_path / "o.pt") == 2
        assert expect[what] in capsys.readouterr().err
        assert not (tmp_path / "o.pt").exists()


def test_another_model_or_source_exits_2(tmp_path, capsys):
    openpcdet_file(tmp_path / "pp.pth", random_state(layouts.openpcdet_pointpillars()))
    assert _run("--from", "openpcdet", "--model", "second", "--checkpoint", tmp_path / "pp.pth",
                "--out", tmp_path / "o.pt") == 2
    err = capsys.readouterr().err
    assert "does not hold the network of OpenPCDet tools/cfgs/kitti_models/second.yaml" in err
    assert "tensors of ours no reference tensor fills" in err  # SECOND's 3D backbone
    assert _run("--from", "mmdet3d", "--model", "dv_second", "--checkpoint", tmp_path / "pp.pth",
                "--out", tmp_path / "o.pt") == 2
    assert "not an MMDetection3D checkpoint" in capsys.readouterr().err
    assert _run("--from", "mmdet3d", "--model", "pv_rcnn", "--checkpoint", tmp_path / "pp.pth",
                "--out", tmp_path / "o.pt") == 2
    assert "no published network" in capsys.readouterr().err
    state = random_state(layouts.mmdet3d_dv_second(True))
    mmdet3d_file(tmp_path / "van.pth", state, True, classes=("Car", "Van"))
    assert _run("--from", "mmdet3d", "--model", "dv_second", "--checkpoint", tmp_path / "van.pth",
                "--out", tmp_path / "o.pt") == 2
    assert "its classes ['Car', 'Van'] are not those of a published config" in capsys.readouterr().err
    mmdet3d_file(tmp_path / "car.pth", state, True, classes=("Car",))  # the Car config's classes, 3-class tensors
    assert _run("--from", "mmdet3d", "--model", "dv_second", "--checkpoint", tmp_path / "car.pth",
                "--out", tmp_path / "o.pt") == 2
    err = capsys.readouterr().err
    assert "second_dv_secfpn_8xb6-80e_kitti-3d-car.py" in err and "bbox_head.conv_cls.weight (18, 512, 1, 1)" in err
    assert not (tmp_path / "o.pt").exists()


def test_dv_second_car_config_imports_into_a_one_class_head(tmp_path):
    """MMDetection3D's Car config: the 3-class network's tensors but the Car anchor set's head channels
    (2 anchors per cell); the Car anchors are the 3-class head's."""
    shapes = layouts.mmdet3d_dv_second(True)
    for name, per_anchor in (("conv_cls", 1), ("conv_reg", 7), ("conv_dir_cls", 2)):
        shapes[f"bbox_head.{name}.weight"] = (2 * per_anchor, *shapes[f"bbox_head.{name}.weight"][1:])
        shapes[f"bbox_head.{name}.bias"] = (2 * per_anchor,)
    mmdet3d_file(tmp_path / "car.pth", random_state(shapes), True, classes=("Car",))
    ckpt = torch.load(tmp_path / "car.pth", weights_only=True)  # as the mmcv 1.x runner saved it (the published file)
    ckpt["meta"] = {"mmdet3d_version": "0.1.0", "CLASSES": ("Car",)}
    torch.save(ckpt, tmp_path / "car.pth")
    info = import_checkpoint(tmp_path / "car.pth", "mmdet3d", "dv_second", tmp_path / "car.pt")
    assert info["classes"] == ["Car"] and info["config"].endswith("second_dv_secfpn_8xb6-80e_kitti-3d-car.py")
    head = zoo.load_checkpoint(tmp_path / "car.pt")[0].head
    three = zoo.build("dv_second", "kitti").head
    assert head.cfg.classes == ("Car",) and head.cfg.sizes == ((3.9, 1.6, 1.56),) and head.cfg.bottoms == (-1.78,)
    torch.testing.assert_close(head.anchors, three.anchors.reshape(-1, 3, 2, 7)[:, 2].reshape(-1, 7))


def test_a_pickle_that_runs_code_is_refused(tmp_path, capsys):
    torch.save({"model_state": torch.nn.Linear(2, 2)}, tmp_path / "evil.pth")  # a pickled module object
    assert _run("--from", "openpcdet", "--model", "second", "--checkpoint", tmp_path / "evil.pth",
                "--out", tmp_path / "o.pt") == 2
    assert "refused" in capsys.readouterr().err
