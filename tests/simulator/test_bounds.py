"""Bounds sets: probes of reference scenarios with one axis moved, their rows, held streams and bad input."""
import numpy as np
import pytest

from harness.core.kitti import read_points
from simulator.bounds import AXIS_RANGES, REFERENCES, Probe, check_probes, reference_value
from simulator.dataset import GenerateConfig, _check_instances, generate, plan_jobs
from simulator.frame import INSTANCE_COLUMNS, ROW_COLUMNS, make_frame, row_columns
from simulator.lidar import LidarSpec
from simulator.space import SLOW_PAINTS, instances, sweep_points, sweep_weather

SCENARIO = "120-60_suv_black"


def _cfg(probes, seed=3):
    return GenerateConfig("bounds", 0, ("Sweep",), seed, LidarSpec(), space=_check_instances(
        "bounds", 1, None, None, None, probes))


def _frame(tmp_path, cfg, instance, offset=5):
    """The frame ``offset`` 10 Hz steps after the lane change of the given instance."""
    job = [j for j in plan_jobs(cfg) if j.instance == instance and j.in_window][offset]
    row, files = make_frame(tmp_path / str(instance), cfg, job)
    return row, read_points(files[0])


def test_reference_scenarios_and_values():
    assert len(REFERENCES) == 8 and {r.slow_body for r in REFERENCES.values()} == {"sedan", "suv"}
    study = REFERENCES["90-60_sedan_silver"].instance()
    assert (study.ego_speed_kmh, study.slow_speed_kmh, study.cutout_gap_m, study.slow_reflectance) == (90, 60, 10, 0.57)
    assert REFERENCES[SCENARIO].instance(0.3).slow_reflectance == 0.3
    assert REFERENCES[SCENARIO].instance().slow_paint == "black"
    assert reference_value(SCENARIO, "reflectance") == SLOW_PAINTS["black"][1]
    assert reference_value(SCENARIO, "fog") == 2000 and reference_value(SCENARIO, "rain") == 0
    assert AXIS_RANGES["reflectance"][:2] == (0.02, 0.8)


def test_probe_rows_weather_and_held_streams(tmp_path):
    """Rain 0 and road water 0 are the reference scenario itself: with one noise seed, the same scan; another
    seed another scan; fog and reflectance probes carry their values."""
    probes = [Probe(SCENARIO, "rain", 0.0), Probe(SCENARIO, "water", 0.0), Probe(SCENARIO, "water", 0.0, 1),
              Probe(SCENARIO, "fog", 80.0), Probe(SCENARIO, "reflectance", 0.7)]
    cfg = _cfg(probes)
    assert all(j.in_window for j in plan_jobs(cfg))  # no lead-in: every frame from the lane change on
    assert row_columns(cfg)[:len(ROW_COLUMNS) + len(INSTANCE_COLUMNS)] == ROW_COLUMNS + INSTANCE_COLUMNS
    assert [p.axis for p in sweep_points(cfg.space, 3)] == ["rain", "water", "water", "fog", "reflectance"]
    assert sweep_weather(probes[4].point()) == sweep_weather(probes[1].point())  # clear, dry
    assert instances(cfg.space, 3)[4].slow_reflectance == 0.7
    rows, scans = zip(*(_frame(tmp_path, cfg, i) for i in range(5)))
    assert np.array_equal(scans[0], scans[1]) and not np.array_equal(scans[1], scans[2])
    for row, p in zip(rows, probes):
        assert (row["reference_scenario"], row["sweep_axis"], row["axis_value"], row["noise_seed"]) == \
               (p.scenario, p.axis, p.value, p.noise_seed)
        assert row["split"] == "test" and row["weather"] == "Sweep" and row["sc_slow_body"] == "suv"
    assert rows[3]["fog_mor_m"] == 80.0 and rows[4]["sc_slow_reflectance"] == 0.7
    # the same scenario step: the same trajectory in every probe
    assert len({r["slow_car_distance_m"] for r in rows}) == 1


def test_bad_probes_are_named(tmp_path):
    with pytest.raises(ValueError, match="unknown reference scenario 'bus'"):
        check_probes([Probe("bus", "rain", 1.0)])
    with pytest.raises(ValueError, match="unknown axis 'snow'"):
        check_probes([Probe(SCENARIO, "snow", 1.0)])
    with pytest.raises(ValueError, match="axis fog: value 20.0 outside 50.0-2000.0 m"):
        check_probes([Probe(SCENARIO, "fog", 20.0)])
    with pytest.raises(ValueError, match="noise seed"):
        check_probes([Probe(SCENARIO, "rain", 1.0, -1)])
    with pytest.raises(ValueError, match="at least one probe"):
        check_probes([])
    with pytest.raises(ValueError, match="bounds preset needs probes"):
        generate(tmp_path / "x", preset="bounds", progress=False)
    with pytest.raises(ValueError, match="probes go with the bounds preset"):
        generate(tmp_path / "x", preset="sweep", probes=[Probe(SCENARIO, "rain", 1.0)], progress=False)
