"""A stage of `run` is reused only when its outputs are the files it wrote."""
import json

from harness.stages import Stages


def make_stage(root):
    """A stage writing one file and a folder of three; returns (Stages, run it, its calls)."""
    calls = []

    def fn():
        calls.append(sorted(p.name for p in (root / "pred").glob("*")) if (root / "pred").is_dir() else [])
        (root / "pred").mkdir(exist_ok=True)
        for i in range(3):
            if not (root / "pred" / f"{i:06d}.txt").is_file():  # resumes: only what is missing is made
                (root / "pred" / f"{i:06d}.txt").write_text(f"Car {i}\n")
        (root / "pred" / ".lock").write_text("")
        (root / "model.onnx").write_bytes(b"onnx" * 100)
        return {"n": 3}
    stages = Stages(root, progress=False)
    return stages, lambda: stages.run("predict_x", {"k": 1}, fn, outputs=[root / "model.onnx", root / "pred"]), calls


def test_outputs_are_hashed_and_a_damaged_one_reruns_the_stage(tmp_path, capsys):
    stages, run, calls = make_stage(tmp_path)
    assert run()["n"] == 3 and len(calls) == 1
    rec = json.loads((tmp_path / ".stages" / "predict_x.json").read_text())
    assert sorted(rec["outputs"]) == ["model.onnx", "pred/000000.txt", "pred/000001.txt", "pred/000002.txt"]
    (tmp_path / "pred" / ".lock").write_text("held")  # hidden bookkeeping files do not count
    run()
    assert len(calls) == 1 and capsys.readouterr().err == ""
    damage = [(lambda: (tmp_path / "model.onnx").write_bytes(b"onnx"), "model.onnx is not the file the stage wrote "
               "(now 4 bytes)"),
              (lambda: (tmp_path / "pred" / "000001.txt").write_text(""), "pred/000001.txt is not the file the stage "
               "wrote (now 0 bytes)"),
              (lambda: (tmp_path / "pred" / "000002.txt").unlink(), "pred/000002.txt is missing")]
    for harm, line in damage:
        harm()
        run()
        assert f"[redo] predict_x: {line}; running the stage again" in capsys.readouterr().err
        assert (tmp_path / "pred" / "000001.txt").read_text() == "Car 1\n"
        assert (tmp_path / "model.onnx").read_bytes() == b"onnx" * 100
    assert [len(c) for c in calls] == [0, 4, 3, 3]  # a changed file is removed before the stage runs again
    run()
    assert len(calls) == 4  # made anew: current again


def test_a_record_without_output_hashes_reruns_its_stage(tmp_path, capsys):
    stages, run, calls = make_stage(tmp_path)
    run()
    path = tmp_path / ".stages" / "predict_x.json"
    rec = json.loads(path.read_text())
    path.write_text(json.dumps({"key": rec["key"], "info": rec["info"]}))  # as an older version wrote it
    run()
    assert len(calls) == 2 and "its record holds no hashes of its outputs" in capsys.readouterr().err
    assert "outputs" in json.loads(path.read_text())
