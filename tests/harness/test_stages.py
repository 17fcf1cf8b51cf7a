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


def test_a_record_without_hashes_of_an_output_reruns_its_stage(tmp_path, capsys):
    stages, run, calls = make_stage(tmp_path)
    run()
    path = tmp_path / ".stages" / "predict_x.json"
    rec = json.loads(path.read_text())
    rec["outputs"] = {"model.onnx": rec["outputs"]["model.onnx"]}  # as a version that recorded only the model
    path.write_text(json.dumps(rec))
    run()
    assert len(calls) == 2
    assert ("[redo] predict_x: its record holds no hashes of pred (an older version wrote it); running the stage "
            "again") in capsys.readouterr().err
    assert sorted(json.loads(path.read_text())["outputs"]) == ["model.onnx", "pred/000000.txt", "pred/000001.txt",
                                                               "pred/000002.txt"]
    run()
    assert len(calls) == 2


def test_big_files_are_read_again_only_when_their_mtime_changed(tmp_path, capsys):
    """``by_stat``: a big output of another size is damaged unread; one whose mtime changed is hashed
    again (an edit of the same size is caught, a touch is not damage); small ones are always hashed."""
    import os

    from harness.stages import BIG_FILE
    scan, label = tmp_path / "data" / "000000.bin", tmp_path / "data" / "000000.txt"
    calls = []

    def fn():
        calls.append(1)
        scan.parent.mkdir(exist_ok=True)
        if not scan.is_file():
            scan.write_bytes(bytes(range(256)) * (BIG_FILE // 256 + 1))
        if not label.is_file():
            label.write_text("Car 0.00 0\n")
        return {}
    stages = Stages(tmp_path, progress=False)
    run = lambda: stages.run("simulate_x", {"k": 1}, fn, outputs=[tmp_path / "data"], by_stat=True)
    run()
    rec = json.loads((tmp_path / ".stages" / "simulate_x.json").read_text())
    assert list(rec["stats"]) == ["data/000000.bin"] and rec["stats"]["data/000000.bin"][0] == scan.stat().st_size
    original, stamp = scan.read_bytes(), scan.stat().st_mtime_ns
    os.utime(scan, ns=(stamp + 10**9, stamp + 10**9))  # touched: hashed again, as written
    run()
    assert len(calls) == 1
    damage = [(lambda: scan.write_bytes(original[:1001]), "data/000000.bin is not the file the stage wrote (now "
               "1001 bytes)"),
              (lambda: scan.write_bytes(original[::-1]), f"data/000000.bin is not the file the stage wrote (now "
               f"{len(original)} bytes)"),
              (lambda: label.write_text("Van 0.00 0\n"), "data/000000.txt is not the file the stage wrote (now 11 "
               "bytes)")]
    for harm, line in damage:
        harm()
        run()
        assert f"[redo] simulate_x: {line}; running the stage again" in capsys.readouterr().err
        assert scan.read_bytes() == original and label.read_text() == "Car 0.00 0\n"
    assert len(calls) == 4
    stamp = scan.stat().st_mtime_ns  # what the check trusts: a scan edited in place with its mtime set back
    scan.write_bytes(original[::-1])
    os.utime(scan, ns=(stamp, stamp))
    run()
    assert len(calls) == 4
