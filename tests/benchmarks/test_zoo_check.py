"""benchmarks/zoo_check.py: the zoo issue's checks from a run folder."""
import json

import pytest

from benchmarks.zoo_check import checks, main, model_rows
from tests.harness.test_report import make_run


def test_rows_from_a_run_folder(tmp_path, capsys):
    run = make_run(tmp_path / "run", models=(("second", 0.1, False), ("parta2", 0.3, True)))
    doc = json.loads((run / "results.json").read_text())
    for name, val in (("second", 80.0), ("parta2", 86.0)):
        doc["models"][name]["train"]["val_ap"] = {"3d_moderate": val, "bev_moderate": val + 5}
    (run / "results.json").write_text(json.dumps(doc))
    rows = model_rows(run)
    res = json.loads((run / "results" / "parta2.json").read_text())
    assert rows["parta2"]["ap3d"] == res["headline"]["3d"]["0.7"]
    assert rows["parta2"]["ap3d_0-30m"] == res["distance"]["3d"]["0.7"]["0-30"]
    # the fixture's proposals are its final boxes: the same AP, so "final > proposal" fails
    assert rows["parta2"]["ap3d_proposals"] == pytest.approx(rows["parta2"]["ap3d"])
    assert "ap3d_proposals" not in rows["second"]
    assert main([str(run)]) == 0
    out = capsys.readouterr().out
    assert "pass  parta2: val AP >= SECOND: 86.0 vs 80.0" in out
    assert "FAIL  second: val AP >= 85: 80.0" in out
    assert "FAIL  parta2: final AP > proposal AP" in out


def test_checks_by_hand():
    bins = lambda a, b, c: {"ap3d_0-30m": a, "ap3d_30-50m": b, "ap3d_50-80m": c}
    rows = {"second": {"val_ap": 90.0, "ap3d": 70.0, **bins(90, 80, 60)},
            "dv_second": {"val_ap": 88.0, "ap3d": 70.0, **bins(90, 80, 60)},
            "mvx_net": {"val_ap": 89.0, "ap3d": 60.0, **bins(85, 69, 60)},
            "point_rcnn": {"val_ap": 91.0, "ap3d": 72.0, "ap3d_proposals": 65.0, "recall_roi@0.7": 80.0,
                           "recall_rcnn@0.7": 79.0, **bins(70, 75, 50)}}
    got = {c: ok for c, ok, _ in checks(rows)}
    assert got["dv_second: val AP >= 85"] and got["point_rcnn: val AP >= SECOND"]
    assert got["point_rcnn: final AP > proposal AP"] and not got["point_rcnn: recall@0.7 RCNN > RoI"]
    assert got["mvx_net: val AP >= DV-SECOND"]
    assert not got["mvx_net: within 10 of DV-SECOND in every bin"]  # 30-50 m: 69 vs 80
    assert not got["point_rcnn: 0-30 m AP >= 30-50 m AP"]
    rows["mvx_net"]["ap3d_30-50m"] = 70.0
    assert {c: ok for c, ok, _ in checks(rows)}["mvx_net: within 10 of DV-SECOND in every bin"]


def test_not_a_run_folder(tmp_path, capsys):
    assert main([str(tmp_path)]) == 2
    assert "no results.json" in capsys.readouterr().err


def test_draw_spread_and_separated_rankings(tmp_path, capsys):
    from benchmarks.zoo_check import draw_spread, separated
    run = make_run(tmp_path / "run", models=(("second", 0.1, False), ("parta2", 0.3, True)))
    doc = json.loads((run / "results.json").read_text())
    draw = lambda tag, val, ap: {"tag": tag, "seed": 0, "val_ap": {"3d_moderate": val}, "headline": {"3d": {"0.7": ap}}}
    doc["draws"] = {"second": [draw("second", 80.0, 60.0), draw("second.seed1", 84.0, 50.0)],
                    "parta2": [draw("parta2", 86.0, 58.0), draw("parta2.seed1", 85.0, 52.0)]}
    (run / "results.json").write_text(json.dumps(doc))
    spread = draw_spread(run)
    assert spread["second"] == {"val_ap": [80.0, 84.0], "ap3d": [60.0, 50.0]}
    assert separated(spread, "val_ap") == [("parta2", "second", True)]  # 85 > 84
    assert separated(spread, "ap3d") == [("second", "parta2", False)]  # means 55 vs 55: 50 < 58
    assert main([str(run), "--json", str(tmp_path / "z.json")]) == 0
    out = capsys.readouterr().out
    assert "| second | 2 | 82.0 | 80.0-84.0 | 55.0 | 50.0-60.0 |" in out
    assert "val AP, rankings beyond the draws: parta2 > second" in out
    assert "AP3D @0.7, within the draws (no ranking): second ~ parta2" in out
    assert json.loads((tmp_path / "z.json").read_text())["separated"]["val_ap"] == [["parta2", "second", True]]


def test_val_ap_is_the_run_val_set_where_there_is_one(tmp_path, capsys):
    """The README's val column and tables/draws.csv read the run's val set; the checks read the same, and the
    checkpoint's own val_ap only for a run without a val set."""
    from benchmarks.zoo_check import draw_spread, val_ap
    run = make_run(tmp_path / "run", models=(("second", 0.1, False), ("parta2", 0.3, True)))
    doc = json.loads((run / "results.json").read_text())
    for name, run_val, ckpt in (("second", 88.0, 85.7), ("parta2", 87.2, 86.4)):
        doc["models"][name]["train"]["val_ap"] = {"3d_moderate": ckpt}
        doc["models"][name]["val"] = {"3d_moderate": run_val, "n_frames": 300}
    doc["draws"] = {"second": [{"tag": "second", "val_ap": {"3d_moderate": 85.7}, "val": {"3d_moderate": 88.0},
                                "headline": {"3d": {"0.7": 70.0}}},
                               {"tag": "second.seed1", "val_ap": {"3d_moderate": 83.8},
                                "headline": {"3d": {"0.7": 68.0}}}]}
    (run / "results.json").write_text(json.dumps(doc))
    assert model_rows(run)["second"]["val_ap"] == 88.0
    assert model_rows(run)["parta2"]["val_ap"] == 87.2
    assert draw_spread(run)["second"]["val_ap"] == [88.0, 83.8]  # the second draw has no run val: its checkpoint's
    assert val_ap({"train": {"val_ap": 77.0}}) == 77.0 and val_ap({}) is None
    assert main([str(run)]) == 0
    assert "FAIL  parta2: val AP >= SECOND: 87.2 vs 88.0" in capsys.readouterr().out
