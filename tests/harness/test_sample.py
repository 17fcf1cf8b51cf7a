import json

import pandas as pd
import pytest

from harness import report
from harness.cli import main
from harness.kitti import KittiError
from harness.sample import publish_sample
from tests.harness.test_report import make_run


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A rendered fake run of the default profile, with a checkpoint, an ONNX file and predictions."""
    root = make_run(tmp_path_factory.mktemp("run"))
    summary = json.loads((root / "results.json").read_text())
    (root / "results.json").write_text(json.dumps({**summary, "profile": "default"}))
    (root / "models").mkdir()
    (root / "models" / "alpha.onnx").write_bytes(b"onnx")
    report.render(root)
    return root


def test_sample_holds_the_report_tables_and_figures_only(run_dir, tmp_path):
    dest = publish_sample(run_dir, tmp_path / "sample")
    names = {str(p.relative_to(dest)) for p in dest.rglob("*") if p.is_file()}
    assert {"report.md", "index.html", "tables/weather_headline.csv", "figures/heatmap.png"} <= names
    assert all(n in ("report.md", "index.html") or n.startswith(("tables/", "figures/")) for n in names)
    assert not any(n.endswith((".onnx", ".pt", ".json", ".txt")) for n in names)
    assert (dest / "index.html").read_bytes() == (run_dir / "index.html").read_bytes()


def test_sample_numbers_are_the_runs_results(run_dir, tmp_path):
    dest = tmp_path / "sample"
    assert main(["--quiet", "report", str(run_dir), "--sample", str(dest)]) == 0
    summary = json.loads((run_dir / "results.json").read_text())
    overview = pd.read_csv(dest / "tables" / "overview.csv").set_index("model")
    headline = pd.read_csv(dest / "tables" / "weather_headline.csv").set_index("weather")
    md = (dest / "report.md").read_text()
    for name, model in summary["models"].items():
        res = json.loads((run_dir / model["results"]).read_text())
        assert overview.loc[name, "AP3D"] == pytest.approx(res["headline"]["3d"]["0.7"])
        assert overview.loc[name, "ORT p50 ms"] == pytest.approx(model["runtime"]["onnxruntime"]["latency_ms_p50"])
        for weather, row in res["groups_by"]["weather"]["rows"].items():
            assert headline.loc[weather, name] == pytest.approx(row["headline"]["3d"]["0.7"])
            assert f"{row['headline']['3d']['0.7']:.1f} [" in md


def test_a_new_sample_replaces_the_old_one(run_dir, tmp_path):
    dest = tmp_path / "sample"
    (dest / "tables").mkdir(parents=True)
    (dest / "tables" / "stale.csv").write_text("old")
    publish_sample(run_dir, dest)
    assert not (dest / "tables" / "stale.csv").exists() and (dest / "report.md").is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["sample"]  # no temp folder left


def test_a_quick_run_is_refused_and_nothing_written(tmp_path, capsys):
    root = make_run(tmp_path / "run")  # the fake run's profile is quick
    report.render(root)
    with pytest.raises(KittiError, match="quick-profile"):
        publish_sample(root, tmp_path / "sample")
    assert main(["report", str(root), "--sample", str(tmp_path / "sample")]) == 2
    assert "results.json" in capsys.readouterr().err
    assert not (tmp_path / "sample").exists()
