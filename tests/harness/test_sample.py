import json
import shutil
from pathlib import Path

import pandas as pd
import pytest

from harness import report
from harness.cli import main
from harness.core.kitti import KittiError
from harness.sample import MANIFEST, publish_sample, sample_files
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
    names = {str(p.relative_to(dest)) for p in dest.rglob("*") if p.is_file()} - {MANIFEST}
    assert json.loads((dest / MANIFEST).read_text())["files"] == sorted(names)  # what a later publish may replace
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
        # the CSVs hold the numbers rounded to 4 decimals as they are written
        assert overview.loc[name, "AP3D"] == round(res["headline"]["3d"]["0.7"], 4)
        assert overview.loc[name, "ORT p50 ms"] == round(model["runtime"]["onnxruntime"]["latency_ms_p50"], 4)
        for weather, row in res["groups_by"]["weather"]["rows"].items():
            assert headline.loc[weather, name] == round(row["headline"]["3d"]["0.7"], 4)
            assert f"{row['headline']['3d']['0.7']:.1f} [" in md


def _older_sample_with(dest: Path, rel: str) -> None:
    """Make the sample in ``dest`` one whose run also wrote ``rel`` (a table or figure this run has not)."""
    (dest / rel).write_text("old")
    manifest = json.loads((dest / MANIFEST).read_text())
    (dest / MANIFEST).write_text(json.dumps({"files": sorted(manifest["files"] + [rel])}))


def test_a_new_sample_replaces_the_old_one(run_dir, tmp_path):
    dest = publish_sample(run_dir, tmp_path / "sample")
    _older_sample_with(dest, "tables/stale.csv")
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


def _snapshot(root: Path) -> dict:
    """Every entry under ``root``: its bytes (files), its target (links) or None (folders)."""
    def content(p: Path):
        return f"-> {p.readlink()}" if p.is_symlink() else p.read_bytes() if p.is_file() else None
    return {str(p.relative_to(root)): content(p) for p in sorted(root.rglob("*"))}


def _refused_destination(kind: str, run: Path, root: Path) -> Path:
    """A --sample folder that must be refused: the run's parent or the run itself, a data set, a file, a link."""
    if kind == "parent":
        return run.parent
    if kind == "run":
        return run
    if kind == "data set":
        return Path(shutil.copytree(run / "data" / "sotif", root / "dataset"))
    if kind == "file":
        (root / "sample").write_text("not a folder\n")
    elif kind == "link":
        (root / "sample").symlink_to(run / "tables", target_is_directory=True)
    return root / "sample"


@pytest.mark.parametrize("kind,reason", [("parent", "holds the run folder"), ("run", "holds the run folder"),
                                         ("data set", "not a previous sample"), ("file", "is a file"),
                                         ("link", "symbolic link")])
def test_a_destination_that_is_not_a_sample_is_refused_and_left_as_it_was(run_dir, tmp_path, capsys, kind, reason):
    run = Path(shutil.copytree(run_dir, tmp_path / "par" / "run"))
    (tmp_path / "par" / "notes.txt").write_text("my notes\n")
    dest = _refused_destination(kind, run, tmp_path)
    before = _snapshot(tmp_path)
    with pytest.raises(ValueError, match=reason):
        publish_sample(run, dest)
    try:
        rc = main(["--quiet", "report", str(run), "--sample", str(dest)])
    except SystemExit as stop:  # the argument parser's refusal (a file given as the folder)
        rc = stop.code
    err = capsys.readouterr().err
    assert rc == 2 and f"{dest}: " in err and "Traceback" not in err
    assert reason in err or (kind == "file" and "is a file, expected a folder" in err)
    assert _snapshot(tmp_path) == before  # the run, the notes and the destination byte for byte


@pytest.mark.parametrize("exists", [False, True])
def test_a_new_or_empty_folder_becomes_the_sample(run_dir, tmp_path, exists):
    dest = tmp_path / "reports" / "sample"
    if exists:
        dest.mkdir(parents=True)
    assert main(["--quiet", "report", str(run_dir), "--sample", str(dest)]) == 0
    assert (dest / "index.html").read_bytes() == (run_dir / "index.html").read_bytes()
    assert sorted(p.name for p in dest.parent.iterdir()) == ["sample"]


def test_a_previous_sample_is_replaced_whole(run_dir, tmp_path):
    dest = publish_sample(run_dir, tmp_path / "sample")
    _older_sample_with(dest, "figures/gone.png")
    (dest / "tables" / "kitti_ap.csv").write_text("old")
    (dest / "report.md").unlink()  # a partial sample is a sample still
    assert main(["--quiet", "report", str(run_dir), "--sample", str(dest)]) == 0
    assert sorted(map(str, (p.relative_to(dest) for p in dest.rglob("*") if p.is_file()))) == \
        sorted(map(str, sample_files(run_dir) + [Path(MANIFEST)]))
    assert (dest / "tables" / "kitti_ap.csv").read_bytes() == (run_dir / "tables" / "kitti_ap.csv").read_bytes()


@pytest.mark.parametrize("rel", ["tables/mine.csv", "figures/photo.png"])
def test_a_file_a_sample_did_not_write_is_never_deleted(run_dir, tmp_path, rel):
    dest = publish_sample(run_dir, tmp_path / "sample")
    (dest / rel).write_text("mine")
    with pytest.raises(ValueError, match=rf"sample: is not empty and not a previous sample \(it holds {rel}"):
        publish_sample(run_dir, dest)
    assert (dest / rel).read_text() == "mine"


def test_a_folder_published_before_the_manifest_is_replaced_only_when_it_holds_sample_files(run_dir, tmp_path):
    legacy = publish_sample(run_dir, tmp_path / "legacy")
    (legacy / MANIFEST).unlink()  # as the repository's sample was published
    publish_sample(run_dir, legacy)
    assert (legacy / MANIFEST).is_file()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "report.md").write_text("my report")  # a report.md but no index.html: not a sample
    with pytest.raises(ValueError, match=r"mine: is not empty and not a previous sample \(it holds report\.md"):
        publish_sample(run_dir, mine)
    assert (mine / "report.md").read_text() == "my report"
