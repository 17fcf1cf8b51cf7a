"""The scenario-space stages of a run: instance counts per profile, the sweep set's simulation key (a whole run
with a sweep set: tests/harness/test_run.py's end to end)."""
import json
from dataclasses import replace

import simulator
from harness import run as run_mod
from harness.run import DATA_PARTS, PROFILES, RunConfig
from harness.stages import Stages, config_hash
from simulator.dataset import GENERATOR_VERSION

TINY = RunConfig("test", "tiny", train_frames=6, sotif_frames=21, epochs=1, workers=1, bootstrap=5, runtime_frames=2,
                 jobs=1)


def test_profiles_set_instance_counts():
    # quick: the study's 42-frame set and a small sweep; default: the counts its cost was chosen for
    assert (PROFILES["quick"].sotif_instances, PROFILES["quick"].sweep_instances) == (None, 3)
    assert (PROFILES["default"].sotif_instances, PROFILES["default"].sweep_instances) == (2, 30)
    assert TINY.sotif_instances is None and TINY.sweep_instances is None  # the study's set, no sweep


def fake_generate(calls):
    def generate(out, **kwargs):
        calls.append(kwargs)
        for part in DATA_PARTS:
            (out / part).mkdir(parents=True, exist_ok=True)
        (out / "meta" / "dataset.json").write_text(json.dumps(kwargs, default=str))
        return out
    return generate


def test_the_sweep_set_is_simulated_with_its_instances_and_keyed_by_them(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(simulator, "generate", fake_generate(calls))
    cfg = replace(TINY, seed=4, sotif_instances=2, sweep_instances=3)
    stages = Stages(tmp_path, progress=False)
    run_mod.simulate_set(stages, cfg, tmp_path / "data", "sweep")
    run_mod.simulate_set(stages, cfg, tmp_path / "data", "sotif")
    sweep, sotif = calls
    assert sweep["preset"] == "sweep" and sweep["instances"] == 3 and sweep["frames"] is None and sweep["seed"] == 2004
    # an instance set is not capped by frames; with the run's own val set it is all test (val_share 0)
    assert sotif["preset"] == "sotif" and sotif["instances"] == 2 and sotif["frames"] is None and sotif["seed"] == 4
    assert sweep["force"] is True and sotif.get("val_share") == sweep.get("val_share") == (0.0 if cfg.val_frames else None)
    key = {"preset": "sweep", "frames": None, "seed": 2004, "lidar": "physics", "generator": GENERATOR_VERSION,
           "instances": 3, **({"val_share": 0.0} if cfg.val_frames else {})}
    assert stages.record("simulate_sweep")["key"] == config_hash(key)
    run_mod.simulate_set(stages, replace(cfg, sweep_instances=4), tmp_path / "data", "sweep")
    assert len(calls) == 3 and calls[-1]["instances"] == 4  # another instance count simulates again


def test_the_studys_set_keeps_its_key_and_call(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(simulator, "generate", fake_generate(calls))
    stages = Stages(tmp_path, progress=False)
    run_mod.simulate_set(stages, TINY, tmp_path / "data", "sotif")
    assert "instances" not in calls[0]  # a simulator without instances is called as it always was
    key = {"preset": "sotif", "frames": 21, "seed": 0, "lidar": "physics", "generator": GENERATOR_VERSION}
    assert stages.record("simulate_sotif")["key"] == config_hash(key)
    run_mod.simulate_set(Stages(tmp_path / "one", progress=False), replace(TINY, sotif_instances=1),
                         tmp_path / "one" / "data", "sotif")
    assert calls[1] == calls[0]  # one instance per weather in a config: the study's set, as run --instances 1 makes it


def test_the_model_summary_carries_the_scenario_space(tmp_path, monkeypatch):
    from tests.harness.conftest import centroid_detector
    from tests.harness.test_report import make_run
    root = make_run(tmp_path / "run", models=(("alpha", 0.1, False),))
    (root / "models").mkdir()
    centroid_detector(root / "models" / "alpha.onnx")
    monkeypatch.setattr(run_mod, "_checkpoint_meta", lambda ckpt: {k: None for k in (
        "params", "epochs", "final_loss", "val_ap", "val_history", "train_seconds")})
    probe = {"onnxruntime": {"latency_ms_p50": 120.0, "latency_ms_p90": 150.0}, "seconds": 1.0}
    summary = run_mod._model_summary(TINY, root, "alpha", {"seconds": 2.0}, {"latency_ms_p50": 99.0}, probe)
    view = summary["sotif_space"]["sotif"]
    system = [r for r in view["instances"] if r["verdict"] == "system"]
    assert {r["latency_ms"] for r in system} == {150.0}  # the probe's p90, not the prediction stage's
    assert view["threshold"] == summary["sotif"]["ClearNoon"]["threshold"]
    assert [r["instance"] for r in system] == list(summary["sotif"])
    assert "sweep" not in summary["sotif_space"] and set(summary["calibration"]) == {"0.7", "0.5"}


def test_the_sweep_set_is_predicted_and_evaluated_by_condition(tmp_path):
    import numpy as np
    from harness.core import kitti
    from harness.run_space import SWEEP_GROUPS, predict_eval_sweep
    from tests.harness.conftest import centroid_detector, make_dataset
    data = make_dataset(tmp_path / "data" / "sweep", n_frames=4, weathers=("Sweep",))
    meta = kitti.read_frames_meta(data / "meta" / "frames.csv")
    meta = meta.assign(instance=np.arange(4), instance_key=[f"Sweep#{i}" for i in range(4)],
                       sweep_axis=["rain", "rain", "fog", "water"], rain_rate_mmh=[0.0, 50.0, 0.0, 0.0],
                       fog_mor_m=[0.0, 0.0, 80.0, 0.0], road_water=[0.0, 0.0, 0.0, 0.8],
                       precipitation_class=["dry", "rain", "dry", "wet"])
    kitti.write_frames_meta(data / "meta" / "frames.csv", meta)
    (tmp_path / "models").mkdir()
    centroid_detector(tmp_path / "models" / "alpha.onnx")
    predict_eval_sweep(Stages(tmp_path, progress=False), TINY, tmp_path, "alpha", "data-hash", "onnxruntime")
    assert len(list((tmp_path / "predictions_sweep" / "alpha").glob("*.txt"))) == 4
    res = json.loads((tmp_path / "results" / "alpha.sweep.json").read_text())
    assert set(res["groups_by"]) == set(SWEEP_GROUPS) and set(res["groups_by"]["sweep_axis"]["rows"]) == {
        "rain", "fog", "water"}
    assert res["groups_by"]["sweep_axis"]["rows"]["rain"]["ci_method"].startswith("bootstrap over instances (2 ")
