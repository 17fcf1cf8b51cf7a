"""The benchmark pipeline on a tiny configuration: end to end, skip when current, resume."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dataclasses import replace

from harness.run import RunConfig, run

TINY = RunConfig("test", "tiny", train_frames=6, sotif_frames=21, epochs=1, workers=1, bootstrap=5, runtime_frames=2,
                 jobs=1)


def stage_keys(run_dir):
    return {p.stem: p.read_text() for p in (run_dir / ".stages").glob("*.json")}


def test_pipeline_end_to_end_then_skips_then_resumes(tmp_path, monkeypatch):
    out = tmp_path / "run"
    # 1. interrupted after the data is simulated, while training
    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr("harness.train.train", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run(models=["pointpillars"], out=out, progress=False, config=TINY)
    done = stage_keys(out)
    assert set(done) == {"simulate_train", "simulate_sotif"}
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
    for name in two:
        rt = summary["models"][name]["runtime"]
        # measured, not asserted equal: an untrained tiny model's proposal scores tie to the last bit, and
        # which of two tied proposals makes the cut differs between runtimes (exact equality is the
        # models' own ONNX == torch tests, on weights with spread scores)
        agreement = rt["agreement"]
        assert agreement["frames"] == TINY.runtime_frames and 0.0 <= agreement["same_boxes"] <= 1.0
        assert "openvino" in rt  # second runtime, or why not
        assert rt["onnxruntime"]["n_timed"] == TINY.runtime_frames  # timed alone, not during prediction
        assert rt["prediction"]["n_frames"] == len((out / "data/sotif/ImageSets/test.txt").read_text().split())
    assert (out / "models/point_rcnn.onnx").is_file() and (out / "results/point_rcnn.json").is_file()
    for rel in ("config.json", "models/pointpillars.onnx", "predictions/pointpillars/predict.json",
                "results/pointpillars.json", "tables/weather_headline.csv", "report.md", "index.html"):
        assert (out / rel).is_file(), rel
    res = json.loads((out / "results/pointpillars.json").read_text())
    assert set(res["groups_by"]) == {"weather", "time_of_day", "precipitation_class"}
    from harness.kitti import read_frames_meta, read_image_set
    meta = read_frames_meta(out / "data/sotif/meta/frames.csv").set_index("frame_id")
    test_weathers = set(meta.loc[read_image_set(out / "data/sotif/ImageSets/test.txt"), "weather"])
    assert set(res["groups"]["rows"]) == test_weathers and len(test_weathers) > 15
    # 3. nothing changed: every stage is skipped (records untouched), whatever the job count
    before = stage_keys(out)
    run(models=two, out=out, progress=False, config=replace(TINY, jobs=2), jobs=1)
    assert stage_keys(out) == before
    assert json.loads((out / "config.json").read_text())["jobs"] == 1


def test_wall_span_of_overlapping_stages():
    from harness.run import _wall_span
    infos = {"a": {"seconds": 10.0, "finished": 110.0}, "b": {"seconds": 30.0, "finished": 125.0},
             "c": {"seconds": 5.0, "finished": 104.0}}
    assert _wall_span(infos) == 125.0 - 95.0  # b starts first, ends last; a and c overlap it
    assert _wall_span({**infos, "old": {"seconds": 3.0}}) is None  # a record without the stamp


def test_bad_profile_and_model_names():
    with pytest.raises(ValueError, match="unknown profile 'huge'"):
        run(profile="huge")
    with pytest.raises(ValueError, match="unknown model"):
        run(models=["yolo"], profile="quick")


def test_job_processes_end_when_the_run_is_killed(tmp_path):
    # the run's process (here a stand-in) is SIGKILLed while its job process works: the job must not train on
    script = ("import os, sys, time, multiprocessing\n"
              "from concurrent.futures import ProcessPoolExecutor\n"
              "from harness.run import _job_init\n"
              "pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context('spawn'), initializer=_job_init,"
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
