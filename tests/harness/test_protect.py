"""No code runs from a checkpoint, and no output replaces an input or a file of another kind."""
import builtins
import json

import torch

from harness.cli import main
from harness.core import kitti
from harness.dataset import write_synthetic_dataset
from models import zoo


class _WritesAFile:
    """Pickled as a call of ``exec``: unpickling it with ``weights_only=False`` would write ``path``."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return builtins.exec, (f"open({self.path!r}, 'w').write('ran')",)


def crafted_checkpoint(path, marker):
    torch.save({"model": "pointpillars", "profile": "tiny", "state_dict": {}, "epoch": 1,
                "payload": _WritesAFile(marker)}, path)
    return path


def test_a_crafted_checkpoint_is_refused_by_export_and_by_a_resumed_train(tmp_path, capsys):
    marker = tmp_path / "marker"
    evil = crafted_checkpoint(tmp_path / "evil.pt", marker)
    out = tmp_path / "model.onnx"
    assert main(["--quiet", "export", "--model", "pointpillars", "--checkpoint", str(evil), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{evil}: refused: it holds more than tensors and plain data (it refers to exec), so loading it" in err
    assert not marker.exists() and not out.exists()
    # a training folder someone else prepared: the resumed training refuses its checkpoint
    data = write_synthetic_dataset(tmp_path / "data", frames=2, seed=3)
    run = tmp_path / "run"
    run.mkdir()
    ckpt = crafted_checkpoint(run / "checkpoint.pt", marker)
    before = ckpt.read_bytes()
    assert main(["--quiet", "train", "--model", "pointpillars", "--profile", "tiny", "--epochs", "1",
                 "--data", str(data), "--out", str(run), "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert f"{ckpt}: refused: it holds more than tensors" in err and "--force" in err
    assert not marker.exists() and ckpt.read_bytes() == before


def test_the_projects_own_checkpoints_load_safely(tmp_path):
    data = write_synthetic_dataset(tmp_path / "data", frames=3, seed=4, val=1)
    ckpt = tmp_path / "run" / "checkpoint.pt"
    from harness.train import train
    train("pointpillars", data, ckpt.parent, profile="tiny", epochs=1, progress=False)
    state = zoo.read_checkpoint(ckpt)  # weights_only=True: optimizer, scheduler, val AP and all
    assert {"optimizer", "scheduler", "val_ap", "config"} <= set(state) and state["model"] == "pointpillars"
    # another model's training into the same folder is refused and leaves the checkpoint alone
    before = ckpt.read_bytes()
    args = ["--quiet", "train", "--model", "second", "--profile", "tiny", "--epochs", "1", "--data", str(data),
            "--out", str(ckpt.parent), "--workers", "1"]
    assert main(args) == 2
    assert ckpt.read_bytes() == before
    # --force replaces it
    assert main(args + ["--force"]) == 0
    assert zoo.read_checkpoint(ckpt)["model"] == "second"


def test_train_over_another_models_checkpoint_is_refused_naming_both(tmp_path, capsys):
    data = write_synthetic_dataset(tmp_path / "data", frames=2, seed=3)
    run = tmp_path / "run"
    run.mkdir()
    torch.save({"model": "second", "profile": "tiny", "state_dict": {}}, run / "checkpoint.pt")
    before = (run / "checkpoint.pt").read_bytes()
    assert main(["--quiet", "train", "--model", "pointpillars", "--profile", "tiny", "--data", str(data),
                 "--out", str(run)]) == 2
    err = capsys.readouterr().err
    assert f"{run / 'checkpoint.pt'}: is a checkpoint of 'second'; training 'pointpillars' into {run}" in err
    assert (run / "checkpoint.pt").read_bytes() == before


def test_export_refuses_to_write_over_its_checkpoint_or_a_file_of_another_kind(tmp_path, capsys):
    ckpt = tmp_path / "c.pt"
    weights = zoo.build("pointpillars", "tiny").state_dict()
    torch.save({"model": "pointpillars", "profile": "tiny", "state_dict": weights}, ckpt)
    before = ckpt.read_bytes()
    export = ["--quiet", "export", "--model", "pointpillars", "--checkpoint", str(ckpt), "--out"]
    assert main(export + [str(ckpt)]) == 2
    assert f"{ckpt}: is the --checkpoint input {ckpt}; writing an ONNX model there" in capsys.readouterr().err
    assert ckpt.read_bytes() == before
    label = tmp_path / "000000.txt"
    label.write_text("Car 0.00 0 0.0 1 2 3 4 1.5 1.8 4.0 1.0 1.0 20.0 0.0\n")
    assert main(export + [str(label)]) == 2
    assert (f"{label}: exists and is a KITTI label or result file (line 1: 'Car 0.00 0 0.0 1 2 3 4 1.5 1.8 4.0 1.0 "
            "1.0 20.0 0.0'), not an ONNX model; refusing to replace it" in capsys.readouterr().err)
    assert label.read_text().startswith("Car")
    copy = tmp_path / "copy.pt"
    copy.write_bytes(before)
    assert main(export + [str(copy)]) == 2
    assert "a zip archive (a PyTorch checkpoint?)" in capsys.readouterr().err


def test_evaluate_refuses_to_write_onto_a_label_file(tmp_path, dataset, capsys):
    from tests.harness.test_evaluate_cli import copy_as_predictions
    pred = copy_as_predictions(dataset, tmp_path / "pred")
    label = dataset / "training" / "label_2" / "000000.txt"
    before = label.read_text()
    args = ["--quiet", "evaluate", "--labels", str(dataset), "--predictions", str(pred), "--bootstrap", "2", "--output"]
    assert main(args + [str(label)]) == 2
    assert f"{label}: is inside the --labels input {dataset / 'training' / 'label_2'}" in capsys.readouterr().err
    other = tmp_path / "notes.txt"
    other.write_text(before)
    assert main(args + [str(other)]) == 2
    assert f"{other}: exists and is a KITTI label or result file (line 1: 'Car " in capsys.readouterr().err
    assert label.read_text() == before == other.read_text()
    results = tmp_path / "results.json"
    assert main(args + [str(results)]) == 0 and main(args + [str(results)]) == 0  # its own results: replaced
    assert main(args + [str(other), "--force"]) == 0
    assert json.loads(other.read_text())["schema"].startswith("sotif-bench/results/")


def test_exceptions_pickle_with_their_message(tmp_path):
    import pickle
    from harness.infer import ContractError
    from models.export import ExportError
    errors = [kitti.KittiError(tmp_path / "a.bin", "truncated", 3), kitti.KittiError("b.txt", "bad"),
              ContractError(tmp_path / "m.onnx", "not a readable ONNX model"), zoo.CheckpointError("c.pt: bad"),
              ExportError("x: failed")]
    for e in errors:
        again = pickle.loads(pickle.dumps(e))
        assert type(again) is type(e) and str(again) == str(e)
    assert pickle.loads(pickle.dumps(errors[0])).line == 3


def test_a_file_that_is_no_checkpoint_is_named_as_such(tmp_path, capsys):
    for name, content in (("config.json", b'{"model": "pointpillars"}'), ("empty.pt", b""),
                          ("text.pt", b"checkpoint\n")):
        path = tmp_path / name
        path.write_bytes(content)
        out = tmp_path / "model.onnx"
        assert main(["--quiet", "export", "--model", "pointpillars", "--checkpoint", str(path), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert f"{path}: not a checkpoint (neither the zip archive torch.save writes nor a pickle)" in err
        assert not out.exists()
    path = tmp_path / "list.pth"  # a torch file, but of a list: named for what it holds, by import and export alike
    torch.save([1, 2], path)
    for args in (["export", "--model", "pointpillars", "--checkpoint", str(path), "--out", str(tmp_path / "m.onnx")],
                 ["import", "--from", "openpcdet", "--model", "pointpillars", "--checkpoint", str(path), "--out",
                  str(tmp_path / "m.pt")]):
        assert main(["--quiet", *args]) == 2
        assert f"{path}: not a checkpoint (holds a list, not the dict of tensors" in capsys.readouterr().err
    assert not (tmp_path / "m.onnx").exists() and not (tmp_path / "m.pt").exists()
