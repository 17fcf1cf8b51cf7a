"""The benchmark pipeline on a tiny configuration: end to end (with a sweep set), skip when current, resume."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from dataclasses import replace

from harness import provenance
from harness.run import PROFILES, RunConfig, resolve, run

TINY = RunConfig("test", "tiny", train_frames=6, sotif_frames=21, epochs=1, workers=1, bootstrap=5, runtime_frames=2,
                 jobs=1, val_frames=3)


def stage_keys(run_dir):
    return {p.stem: p.read_text() for p in (run_dir / ".stages").glob("*.json")}


def test_pipeline_end_to_end_then_skips_then_resumes(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    # 1. interrupted after the data is simulated, while training
    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr("harness.train.train", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run(models=["pointpillars"], out=out, progress=False, config=TINY)
    done = stage_keys(out)
    assert set(done) == {"simulate_train", "simulate_sotif", "simulate_val"}
    monkeypatch.undo()
    # 2. resumed, two models in two job processes: the simulation is not redone, the rest runs to the report
    calls = []
    import simulator
    real_generate = simulator.generate
    monkeypatch.setattr(simulator, "generate", lambda *a, **k: calls.append(a) or real_generate(*a, **k))
    two = ["pointpillars", "point_rcnn"]
    run(models=two, out=out, progress=False, config=replace(TINY, jobs=2))
    assert calls == []
    summary = json.loads((out / "results.json").read_text())
    assert 0 < summary["wall_seconds"] <= sum(summary["stage_seconds"].values()) + 1
    assert summary["schema"] == "sotif-bench/run/1" and list(summary["models"]) == two
    assert "draws" not in summary and not (out / "tables/draws.csv").exists()  # one draw: the layout of old
    assert summary["models"]["pointpillars"]["train"]["val_history"][0]["epoch"] == 1
    for name in two:
        rt = summary["models"][name]["runtime"]
        # measured, not asserted equal: an untrained tiny model's proposal scores tie to the last bit, and
        # which of two tied proposals makes the cut differs between runtimes (exact equality is the
        # models' own ONNX == torch tests, on weights with spread scores)
        agreement = rt["agreement"]
        assert agreement["frames"] == TINY.runtime_frames and 0.0 <= agreement["same_boxes"] <= 1.0
        assert "openvino" in rt  # second runtime, or why not
        assert rt["onnxruntime"]["n_timed"] == TINY.runtime_frames  # timed alone, not during prediction
        frames_ms = rt["frames_ms"]  # the per-frame figures behind the summary
        assert len(frames_ms["onnxruntime"]) == len(frames_ms["torch_eager"]) == TINY.runtime_frames
        assert rt["onnxruntime"]["latency_ms_p50"] == pytest.approx(np.median(frames_ms["onnxruntime"]))
        assert rt["prediction"]["n_frames"] == len((out / "data/sotif/ImageSets/test.txt").read_text().split())
    assert (out / "models/point_rcnn.onnx").is_file() and (out / "results/point_rcnn.json").is_file()
    for rel in ("config.json", "models/pointpillars.onnx", "predictions/pointpillars/predict.json",
                "results/pointpillars.json", "tables/weather_headline.csv", "report.md", "index.html"):
        assert (out / rel).is_file(), rel
    import pandas as pd
    pairs = pd.read_csv(out / "tables/pairs.csv")  # the two models on the val set and the SOTIF test split
    assert pairs[["model_a", "model_b", "metric"]].values.tolist() == [
        ["pointpillars", "point_rcnn", "val_ap3d_moderate"], ["pointpillars", "point_rcnn", "headline_ap3d"]]
    assert pairs["data"][0] == "val: 3 held-out training-generator frames" and (pairs["n_draws_a"] == 1).all()
    res = json.loads((out / "results/pointpillars.json").read_text())
    assert set(res["groups_by"]) == {"weather", "time_of_day", "precipitation_class"}
    from harness.core.kitti import read_frames_meta, read_image_set
    meta = read_frames_meta(out / "data/sotif/meta/frames.csv").set_index("frame_id")
    test_weathers = set(meta.loc[read_image_set(out / "data/sotif/ImageSets/test.txt"), "weather"])
    assert set(res["groups"]["rows"]) == test_weathers and len(test_weathers) > 15
    # 3. nothing changed: every stage is skipped (records untouched), whatever the job count; the temp
    # files of writes a kill cut short are cleared, files with other names are not
    before = stage_keys(out)
    stale = [out / "models/.pointpillars.onnx.k2x_9q0a.tmp", out / "predictions/pointpillars/.000003.txt.abcdefgh.tmp"]
    for path in stale:
        path.write_bytes(b"half a file")
    (out / ".notes.tmp").write_text("mine")
    run(models=two, out=out, progress=False, config=replace(TINY, jobs=2), jobs=1)
    assert stage_keys(out) == before
    assert not any(path.exists() for path in stale) and (out / ".notes.tmp").read_text() == "mine"
    assert json.loads((out / "config.json").read_text())["jobs"] == 1
    # 4. an evaluator fix that moves numbers evaluates the same predictions again, and nothing else
    monkeypatch.setattr("harness.evaluate.EVALUATOR_VERSION", 1000)
    run(models=two, out=out, progress=False, config=replace(TINY, jobs=2), jobs=1)
    after = stage_keys(out)
    assert {k for k in after if after[k] != before[k]} == {f"evaluate{v}_{m}" for v in ("", "_valset")
                                                           for m in ("pointpillars", "point_rcnn")}
    # 5. two training draws: draw 0 is the run's model, resumed as it is; draw 1 trains with seed 1 into its own files
    run(models=["pointpillars"], out=out, progress=False, config=TINY, seeds=2)
    again = stage_keys(out)
    assert {k for k in again if again[k] != after.get(k)} == {f"{s}_pointpillars.seed1" for s in
                                                              ("train", "export", "predict", "predict_val", "evaluate",
                                                               "predict_valset", "evaluate_valset")}
    assert torch.load(out / "models/pointpillars.seed1/checkpoint.pt", weights_only=True)["seed"] == 1
    for rel in ("models/pointpillars.seed1.onnx", "predictions/pointpillars.seed1/predict.json",
                "results/pointpillars.seed1.json", "tables/draws.csv"):
        assert (out / rel).is_file(), rel
    summary = json.loads((out / "results.json").read_text())
    draws = summary["draws"]["pointpillars"]
    assert [d["seed"] for d in draws] == [0, 1] and draws[0]["results"] == "results/pointpillars.json"
    assert [d["val"]["n_frames"] for d in draws] == [3, 3] and summary["models"]["pointpillars"]["val"]["n_frames"] == 3
    table = pd.read_csv(out / "tables/draws.csv").iloc[0]
    aps = [d["headline"]["3d"]["0.7"] for d in draws]
    close = lambda v: pytest.approx(v, abs=5e-5)  # the CSV holds 4 decimals
    assert table["draws"] == 2 and table["AP3D mean"] == close(np.mean(aps))
    assert table["AP3D min"] == close(min(aps)) and table["AP3D max"] == close(max(aps))
    assert "Training draws" in (out / "report.md").read_text()
    # every epoch names the CPU it ran on (another CPU: another draw), and so do the table and the report
    here = provenance.machine()
    assert [provenance.trained_on(d["val_history"]) for d in draws] == [{here: TINY.epochs}] * 2
    assert table["trained on"] == here
    assert f"- **Machine:** trained (every epoch of the 2 trainings) and latency timed on {here}." in \
        (out / "report.md").read_text()
    # 5b. a sweep set (3 scenario instances) beside the study's SOTIF set: simulated, predicted and judged with the
    # model as it is (nothing before it runs again), with the scenario-space tables and report section
    run(models=["pointpillars"], out=out, progress=False, config=replace(TINY, sweep_instances=3))
    swept = stage_keys(out)
    assert {k for k in swept if swept[k] != again.get(k)} >= {"simulate_sweep"}
    assert not {k for k in swept if swept[k] != again.get(k)} & {"train_pointpillars", "export_pointpillars",
                                                                "predict_pointpillars", "simulate_sotif"}
    model = json.loads((out / "results.json").read_text())["models"]["pointpillars"]
    assert set(model["sotif_space"]) == {"sotif", "sweep"} and set(model["calibration"]) == {"0.7", "0.5"}
    assert len({r["instance"] for r in model["sotif_space"]["sweep"]["instances"]}) >= 2
    assert "sweep_axis" in json.loads((out / "results" / "pointpillars.sweep.json").read_text())["groups_by"]
    for name in ("sotif_instances", "sotif_pass_rates", "sotif_phantoms", "triggering_conditions", "calibration"):
        assert (out / "tables" / f"{name}.csv").is_file()
    assert "SOTIF over the scenario space" in (out / "report.md").read_text()
    # 6. a damaged output reruns its stage, with a line saying so: a truncated ONNX file is exported again
    # (the export may differ in its bytes, and then everything after it runs again), an emptied and a deleted
    # prediction file are predicted again
    onnx_file = out / "models/pointpillars.onnx"
    onnx_file.write_bytes(onnx_file.read_bytes()[:1000])
    test_ids = read_image_set(out / "data/sotif/ImageSets/test.txt")
    emptied = out / f"predictions/point_rcnn/{test_ids[0]}.txt"
    deleted = out / f"predictions/point_rcnn/{test_ids[1]}.txt"
    kept = {p: p.read_text() for p in (emptied, deleted)}
    emptied.write_text("")
    deleted.unlink()
    capsys.readouterr()
    run(models=two, out=out, progress=False, config=replace(TINY, jobs=2), jobs=1)
    err = capsys.readouterr().err
    for line in ("export_pointpillars: models/pointpillars.onnx is not the file the stage wrote (now 1000 bytes)",
                 f"predict_point_rcnn: predictions/point_rcnn/{test_ids[0]}.txt is not the file the stage wrote "
                 "(now 0 bytes) (and 1 more file(s)); running the stage again"):
        assert f"[redo] {line}" in err
    from harness.infer import check_contract
    check_contract(onnx_file)
    assert {p: p.read_text() for p in kept} == kept
    # 7. bad input in a model's job ends the run with its file and problem, in the run's process or in a job's:
    # a scan the data set's record vouches for, as if the simulator had written it so (a damaged scan is
    # simulated again: test_a_changed_or_damaged_data_set_file_is_simulated_again)
    from harness.cli import main
    from harness.core.kitti import KittiError
    scan = out / f"data/sotif/training/velodyne/{test_ids[2]}.bin"
    scan.write_bytes(scan.read_bytes()[:1001])
    vouch_for(out, "simulate_sotif", scan)
    for name in two:
        (out / f"predictions/{name}/{test_ids[2]}.txt").unlink()
    with pytest.raises(KittiError, match=f"{scan}: size 1001 bytes is not a multiple of 16"):
        run(models=two, out=out, progress=False, config=replace(TINY, jobs=2), jobs=1)
    monkeypatch.setitem(PROFILES, "quick", TINY)  # the CLI's profile names: the tiny config behind one
    capsys.readouterr()
    args = ["--quiet", "run", "--profile", "quick", "--models", ",".join(two), "--out", str(out), "--jobs", "2"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert f"sotif-bench run: error: {scan}: size 1001 bytes is not a multiple of 16" in err and "Traceback" not in err


def vouch_for(run_dir, stage, path):
    """Record ``path`` as it is now as the file ``stage`` wrote."""
    from harness.stages import file_digest
    record = run_dir / ".stages" / f"{stage}.json"
    rec, rel = json.loads(record.read_text()), path.relative_to(run_dir).as_posix()
    rec["outputs"][rel] = file_digest(path)
    rec["stats"].pop(rel, None)
    record.write_text(json.dumps(rec))


def van(label_text: str) -> str:
    """A label file's text with its first car labelled Van."""
    lines = label_text.splitlines(keepends=True)
    first = next(i for i, line in enumerate(lines) if line.startswith("Car "))
    return "".join(lines[:first] + ["Van" + lines[first][3:]] + lines[first + 1:])


def test_a_changed_or_damaged_data_set_file_is_simulated_again(tmp_path, monkeypatch, capsys):
    """The data sets are the simulate stages' outputs: an edited label or a truncated scan is removed and
    its frame simulated again, to the same bytes, so nothing after it runs again; a data set whose bytes
    do change runs the stages that read it again."""
    import simulator.dataset as sd
    from harness.evaluate import evaluate
    from harness.core.kitti import frame_path, read_image_set
    from harness.stages import file_digest
    out, sotif = tmp_path / "run", tmp_path / "run/data/sotif"
    go = lambda: run(models=["pointpillars"], out=out, progress=False, config=TINY)
    go()
    before, results = stage_keys(out), (out / "results/pointpillars.json").read_text()
    n_car = json.loads(results)["n_car"]
    made, real_make = [], sd.make_frame
    counted = lambda root, cfg, job: made.append(job.frame_id) or real_make(root, cfg, job)
    monkeypatch.setattr(sd, "make_frame", counted)
    # 1. nothing changed: every stage skipped, no frame made
    go()
    assert stage_keys(out) == before and made == []
    # 2. an edited label and a truncated scan of two test frames, a truncated training scan
    ids = read_image_set(sotif / "ImageSets/test.txt")
    fid = next(i for i in ids if "\nCar " in "\n" + frame_path(sotif, "label_2", i).read_text())
    other = next(i for i in ids if i != fid)
    label, scan = frame_path(sotif, "label_2", fid), frame_path(sotif, "velodyne", other)
    train_scan = frame_path(out / "data/train", "velodyne", "000001")
    kept = {p: p.read_bytes() for p in (label, scan, train_scan)}
    label.write_text(van(label.read_text()))
    for path in (scan, train_scan):
        path.write_bytes(kept[path][:1001])
    stale = evaluate(sotif, out / "predictions/pointpillars", split=sotif / "ImageSets/test.txt", n_bootstrap=1)
    assert stale["n_car"] == n_car - 1  # the results no longer those of the data set
    capsys.readouterr()
    go()
    err = capsys.readouterr().err
    for line in (f"simulate_sotif: data/sotif/training/velodyne/{other}.bin is not the file the stage wrote (now 1001 "
                 "bytes) (and 1 more file(s))", "simulate_train: data/train/training/velodyne/000001.bin is not the "
                 "file the stage wrote (now 1001 bytes)"):
        assert f"[redo] {line}; running the stage again" in err
    assert sorted(made) == sorted([fid, other, "000001"]) and {p: p.read_bytes() for p in kept} == kept
    after = stage_keys(out)
    assert {k for k in after if after[k] != before[k]} == {"simulate_sotif", "simulate_train"}
    assert (out / "results/pointpillars.json").read_text() == results
    # 3. a frame simulated again with other bytes (here its first car labelled Van) changes the test set:
    # prediction and evaluation run again, training does not, and the results count one car less

    def relabelled(root, cfg, job):
        row, files = real_make(root, cfg, job)
        if job.frame_id == fid:
            path = frame_path(root, "label_2", fid)
            path.write_text(van(path.read_text()))
        return row, files
    monkeypatch.setattr(sd, "make_frame", relabelled)
    label.write_text("")
    go()
    again = stage_keys(out)
    assert {k for k in again if again[k] != after[k]} == {"simulate_sotif", "predict_pointpillars",
                                                          "predict_val_pointpillars", "evaluate_pointpillars"}
    assert json.loads((out / "results/pointpillars.json").read_text())["n_car"] == n_car - 1
    # 4. records of the version that hashed meta/dataset.json alone: the simulator checks every frame and
    # makes none, and nothing after it runs again
    for preset in ("train", "sotif"):
        record, meta = out / f".stages/simulate_{preset}.json", out / f"data/{preset}/meta/dataset.json"
        rec = json.loads(record.read_text())
        record.write_text(json.dumps({"key": rec["key"], "info": rec["info"],
                                      "outputs": {meta.relative_to(out).as_posix(): file_digest(meta)}}))
    monkeypatch.setattr(sd, "make_frame", counted)
    made.clear()
    capsys.readouterr()
    go()
    assert ("[redo] simulate_train: its record holds no hashes of data/train/training/velodyne and 5 more output(s) "
            "(an older version wrote it)") in capsys.readouterr().err
    upgraded = stage_keys(out)
    assert made == [] and {k for k in upgraded if upgraded[k] != again[k]} == {"simulate_sotif", "simulate_train"}
    assert "data/sotif/training/label_2/000000.txt" in json.loads(upgraded["simulate_sotif"])["outputs"]


def test_wall_span_of_overlapping_stages():
    from harness.run import _wall_span
    infos = {"a": {"seconds": 10.0, "finished": 110.0}, "b": {"seconds": 30.0, "finished": 125.0},
             "c": {"seconds": 5.0, "finished": 104.0}}
    assert _wall_span(infos) == 125.0 - 95.0  # b starts first, ends last; a and c overlap it
    assert _wall_span({**infos, "old": {"seconds": 3.0}}) is None  # a record without the stamp
    resumed = {**infos, "d": {"seconds": 20.0, "finished": 1020.0}, "e": {"seconds": 5.0, "finished": 1010.0}}
    assert _wall_span(resumed) == 30.0 + 20.0  # the pause between the sessions does not count
    rng = np.random.default_rng(0)  # against a 1 ms grid
    starts, lengths = rng.uniform(0, 50, 12).round(3), rng.uniform(0.5, 8, 12).round(3)
    grid = np.zeros(60000, bool)
    for b, n in zip(starts, lengths):
        grid[int(round(b * 1000)):int(round((b + n) * 1000))] = True
    infos = {str(k): {"seconds": float(n), "finished": float(b + n)} for k, (b, n) in enumerate(zip(starts, lengths))}
    assert _wall_span(infos) == pytest.approx(grid.sum() / 1000, abs=0.01)


def test_a_changed_lidar_model_simulates_the_run_data_again(tmp_path):
    """The run's data folder is its own: a changed simulate key replaces the data set there."""
    from harness.run import simulate_set
    from harness.stages import Stages
    cfg = replace(TINY, train_frames=1)
    stages = Stages(tmp_path, progress=False)
    physics = simulate_set(stages, cfg, tmp_path / "data", "train")
    assert simulate_set(stages, cfg, tmp_path / "data", "train") == physics  # current: skipped
    carla = simulate_set(stages, replace(cfg, lidar_model="carla"), tmp_path / "data", "train")
    meta = json.loads((tmp_path / "data" / "train" / "meta" / "dataset.json").read_text())
    assert carla != physics and meta["config"]["lidar"]["model"] == "carla"


def test_a_second_run_into_the_same_folder_is_refused(tmp_path):
    from harness.core.files import folder_lock
    (tmp_path / "results.json").write_text("{}")
    (tmp_path / ".stages").mkdir()  # a run's folder
    with folder_lock(tmp_path, "run"):
        with pytest.raises(ValueError, match=f"{tmp_path}: another sotif-bench run is writing to this folder"):
            run(models=["pointpillars"], out=tmp_path, progress=False, config=TINY)
    assert (tmp_path / "results.json").read_text() == "{}" and not (tmp_path / "config.json").exists()


def test_eta_of_model_jobs():
    from harness.run import _SAMPLE_MINUTES, _eta_seconds
    m = _SAMPLE_MINUTES
    a, b, c, d = sorted(m, key=m.get, reverse=True)[:4]
    # two slots: a and b started at 0, a ended at 1.5 * its sample time (the machine runs 1.5x slow), c started then
    t_a = 90.0 * m[a]
    starts, ends = {a: 0.0, b: 0.0, c: t_a}, {a: t_a}
    # b has 1.5 * 60 * m[b] - t_a left; c and d queue behind it on whichever slot frees first
    left_b, left_c = 90.0 * m[b] - t_a, 90.0 * m[c]
    expect = max(left_b + 90.0 * m[d], left_c) if left_b <= left_c else max(left_b, left_c + 90.0 * m[d])
    assert _eta_seconds([a, b, c, d], m, starts, ends, t_a, 2) == pytest.approx(expect)
    # one slot, nothing timed yet (a resumed job with little left does not count): sample minutes as they are
    resumed = {**m, a: 0.1}
    assert _eta_seconds([a, b], resumed, {a: 0.0, b: 5.0}, {a: 5.0}, 5.0, 1) == pytest.approx(60.0 * m[b])
    # a resumed run whose jobs are all done but one epoch of b: the ETA is that share, not the full sample times
    nearly = {a: 0.0, b: 0.05 * m[b], c: 0.0, d: 0.0}
    assert _eta_seconds([a, b, c, d], nearly, {a: 0.0, b: 0.0}, {}, 0.0, 2) == pytest.approx(3.0 * m[b])
    # a running job past its expected time counts as ending now
    assert _eta_seconds([a, b], m, {a: 0.0, b: 0.0}, {a: t_a}, 10 * t_a, 2) == 0.0


def test_the_default_run_states_its_eta_before_the_first_job_ends():
    from harness.run import _SAMPLE_MINUTES, _start_eta
    m = _SAMPLE_MINUTES
    order = sorted(m, key=m.get, reverse=True)
    # one slot: the jobs one after the other; two slots: each job, longest first, on the slot that frees first
    assert _start_eta(PROFILES["default"], order, m, 1).startswith(f"== model jobs: about {sum(m.values()):.0f} min ")
    slots = [0.0, 0.0]
    for n in order:
        slots[slots.index(min(slots))] += m[n]
    assert f"about {max(slots):.0f} min" in _start_eta(PROFILES["default"], order, m, 2)
    assert _start_eta(PROFILES["quick"], order, m, 2) == "" and _start_eta(TINY, order, m, 1) == ""


def test_bad_profile_and_model_names():
    with pytest.raises(ValueError, match="unknown profile 'huge'"):
        run(profile="huge")
    with pytest.raises(ValueError, match="unknown model"):
        run(models=["yolo"], profile="quick")


def test_a_folder_of_other_files_is_not_taken_for_a_run(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "report.md").write_text("my report\n")
    (out / "config.json").write_text('{"editor": "vim"}')
    with pytest.raises(ValueError, match=r"mine: holds files \(config\.json, \.\.\.\) but no sotif-bench run"):
        run(profile="quick", models=["pointpillars"], out=out, progress=False)
    assert sorted(p.name for p in out.iterdir()) == ["config.json", "report.md"]
    assert (out / "report.md").read_text() == "my report\n" and (out / "config.json").read_text() == '{"editor": "vim"}'


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_the_full_profile_without_cuda_says_it_trains_on_the_cpu(capsys):
    cfg, _, _ = resolve("full", None, None)
    assert cfg.device == "cpu"
    assert "no CUDA device here: the full profile's kitti models train on the CPU" in capsys.readouterr().err


def test_job_processes_end_when_the_run_is_killed(tmp_path):
    # the run's process (here a stand-in) is SIGKILLed while its job process works: the job must not train on
    script = ("import os, sys, time, multiprocessing\n"
              "from concurrent.futures import ProcessPoolExecutor\n"
              "from harness.jobs import job_init\n"
              "pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context('spawn'), initializer=job_init,"
              " initargs=(1,))\n"
              "print(pool.submit(os.getpid).result(), flush=True)\n"
              "pool.submit(time.sleep, 120).result()\n")
    run_proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True,
                                cwd=Path(__file__).parents[2])
    job = int(run_proc.stdout.readline())

    def running(pid):
        try:
            return open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0] != "Z"
        except FileNotFoundError:
            return False
    assert running(job)
    run_proc.send_signal(signal.SIGKILL)
    run_proc.wait()
    deadline = time.monotonic() + 15
    while running(job) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = running(job)
    if alive:
        os.kill(job, signal.SIGKILL)
    assert not alive


def test_an_interrupted_job_process_takes_no_queued_job():
    # Ctrl-C reaches the job processes too: the running job stops, and a model job that was already
    # queued to the same process is refused instead of training for many minutes
    script = ("import os, signal, time, multiprocessing\n"
              "from concurrent.futures import ProcessPoolExecutor\n"
              "from harness.jobs import job_init\n"
              "from harness.run import _model_job\n"
              "pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context('spawn'), initializer=job_init,"
              " initargs=(1,))\n"
              "pid = pool.submit(os.getpid).result()\n"
              "running = pool.submit(time.sleep, 120)\n"
              "queued = pool.submit(_model_job, None, None, 'pointpillars', None, '', '', 'onnxruntime', False, 1,"
              " False)\n"
              "time.sleep(1.0)\n"
              "t0 = time.monotonic()\n"
              "os.kill(pid, signal.SIGINT)\n"
              "print(type(running.exception()).__name__, type(queued.exception()).__name__,\n"
              "      str(queued.exception()), round(time.monotonic() - t0) < 10, flush=True)\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).parents[2])
    assert out.stdout.split(None, 2)[:2] == ["KeyboardInterrupt", "KeyboardInterrupt"], out.stderr
    assert "the run was interrupted" in out.stdout and out.stdout.strip().endswith("True")


def test_a_warm_started_model_brings_its_sibling_unless_the_run_holds_it(tmp_path, capsys):
    import harness.run as hr
    assert PROFILES["default"].warm_start and PROFILES["quick"].warm_start and not PROFILES["full"].warm_start
    cfg = replace(TINY, warm_start=True)
    assert hr.with_siblings(cfg, tmp_path, ["pv_rcnn", "parta2", "mvx_net"]) == \
        ["pv_rcnn", "parta2", "mvx_net", "second", "dv_second"]
    assert "pv_rcnn starts from second's first stage: second is trained too" in capsys.readouterr().out
    assert hr.with_siblings(cfg, tmp_path, ["second", "pv_rcnn"]) == ["second", "pv_rcnn"]
    assert hr.with_siblings(replace(cfg, warm_start=False), tmp_path, ["pv_rcnn"]) == ["pv_rcnn"]
    (tmp_path / "models" / "second").mkdir(parents=True)
    (tmp_path / "models" / "second" / "checkpoint.pt").write_bytes(b"weights")  # trained by an earlier run
    assert hr.with_siblings(cfg, tmp_path, ["pv_rcnn"], progress=False) == ["pv_rcnn"]
    # with two draws, the second draw's sibling is missing: SECOND trains too
    assert hr.with_siblings(replace(cfg, seeds=2), tmp_path, ["pv_rcnn"], progress=False) == ["pv_rcnn", "second"]


def test_warm_start_trains_the_sibling_first_and_starts_from_it(tmp_path, monkeypatch):
    import harness.run as hr
    cfg = replace(TINY, warm_start=True)
    order = []
    monkeypatch.setattr(hr, "_model_job", lambda c, d, name, *a: order.append(name) or ({}, {}))
    names = ["pv_rcnn", "mvx_net", "point_rcnn", "dv_second", "second"]
    hr._model_jobs(cfg, tmp_path, names, hr.model_recipes(cfg, names), "", "", "onnxruntime", False, 0.0)
    assert order.index("second") < order.index("pv_rcnn") and order.index("dv_second") < order.index("mvx_net")
    with pytest.raises(ValueError, match="--warm-start: pv_rcnn starts from second, which is neither among the models"):
        hr._model_jobs(cfg, tmp_path, ["pv_rcnn"], hr.model_recipes(cfg, ["pv_rcnn"]), "", "", "onnxruntime", False,
                       0.0)
    order.clear()
    cold = replace(cfg, warm_start=False)
    hr._model_jobs(cold, tmp_path, ["pv_rcnn"], hr.model_recipes(cold, ["pv_rcnn"]), "", "", "onnxruntime", False, 0.0)
    assert order == ["pv_rcnn"]  # a cold start needs no sibling
    # the sibling's checkpoint (the same draw's) starts the training, and its digest is in the stage key
    sibling = tmp_path / "models" / "second.seed1" / "checkpoint.pt"
    sibling.parent.mkdir(parents=True)
    sibling.write_bytes(b"weights")
    seen = {}

    def train(*a, **k):
        seen.update(k)
        raise KeyboardInterrupt

    monkeypatch.undo()  # the real model job, with a training that records its arguments
    monkeypatch.setattr("harness.train.train", train)
    with pytest.raises(KeyboardInterrupt):
        hr._model_job(cfg, tmp_path, "pv_rcnn.seed1", hr.model_recipes(cfg, ["pv_rcnn"])["pv_rcnn"], "h", "h",
                      "onnxruntime", False, None, False, 1)
    assert seen["init_from"] == sibling and seen["seed"] == cfg.seed + 1
    recipes = hr.model_recipes(cfg, ["point_rcnn", "mvx_net"])
    assert hr._sibling(recipes["point_rcnn"], "point_rcnn") is None
    assert hr._sibling(recipes["mvx_net"], "mvx_net.seed2") == "dv_second.seed2"


def test_a_changed_graph_code_exports_again_and_trains_nothing(tmp_path, monkeypatch):
    import harness.model_stages as ms
    import harness.run as hr
    from harness.stages import Stages
    calls = []

    def train(name, data, out, **k):
        calls.append("train")
        out.mkdir(parents=True, exist_ok=True)
        (out / "checkpoint.pt").write_bytes(b"weights")
        return out / "checkpoint.pt"

    def export(ckpt, out, expected_model=None, say=None):
        calls.append("export")
        out.write_bytes(b"graph")
        return out

    monkeypatch.setattr("harness.train.train", train)
    monkeypatch.setattr("models.export.export_checkpoint", export)
    stages = Stages(tmp_path, False)
    for code in ("a", "a", "b"):
        monkeypatch.setattr(ms, "graph_code", lambda code=code: code)
        recipe = hr.model_recipes(TINY, ["pointpillars"])["pointpillars"]
        hr._train_export(stages, TINY, tmp_path, recipe, "pointpillars", "data")
    assert calls == ["train", "export", "export"]


def test_a_later_draw_is_not_predicted_on_the_sweep_set(tmp_path, monkeypatch):
    import harness.run as hr
    seen = []
    monkeypatch.setattr(hr, "_train_export", lambda *a, **k: {})
    monkeypatch.setattr(hr, "_predict_eval", lambda *a: seen.append(a[-1]) or {})
    monkeypatch.setattr(hr.valset, "predict_evaluate", lambda *a, **k: None)
    recipe = hr.model_recipes(TINY, ["pointpillars"])["pointpillars"]
    for tag, draw in (("pointpillars", 0), ("pointpillars.seed1", 1)):
        hr._model_job(TINY, tmp_path, tag, recipe, "h", "h", "onnxruntime", False, None, False, draw, "sweep")
    assert seen == ["sweep", None]
