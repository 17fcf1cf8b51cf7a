"""A data set's identity: the content digest simulate records, the run's tables/data_sets.csv and its
comparison with the sample's."""
import hashlib
import json

import pandas as pd

from harness import data_identity
from simulator import generate
from simulator.dataset import content_digest, read_content_digest


def test_content_digest_covers_every_file_but_the_record(tmp_path):
    root = generate(tmp_path / "set", preset="train", frames=2, seed=1, progress=False)
    meta = json.loads((root / "meta" / "dataset.json").read_text())
    derived = ("planes", "testing", "test_as_val", "frames")  # road planes, toolkit views, frame records
    files = sorted(p for p in root.rglob("*") if p.is_file() and not p.is_symlink()
                   and p.name not in ("dataset.json", ".lock") and not set(derived) & set(p.relative_to(root).parts[:-1]))
    want = hashlib.sha256()
    for p in sorted(files, key=lambda p: str(p.relative_to(root))):
        want.update(f"{p.relative_to(root)}\0{hashlib.sha256(p.read_bytes()).hexdigest()}\n".encode())
    assert sorted(meta["files"]) == sorted(str(p.relative_to(root)) for p in files)
    assert meta["content_sha256"] == want.hexdigest() == read_content_digest(root)


def test_digest_changes_with_any_file_and_ignores_order():
    files = {"a/1.bin": "00", "b/2.txt": "11"}
    assert content_digest(files) == content_digest(dict(reversed(list(files.items()))))
    assert content_digest(files) != content_digest({**files, "b/2.txt": "12"})
    assert content_digest(files) != content_digest({"a/1.bin": "00"})


def test_a_set_without_the_key_gets_its_digest_from_the_file_list(tmp_path):
    (tmp_path / "meta").mkdir()
    (tmp_path / "meta" / "dataset.json").write_text(json.dumps({"files": {"x": "ab"}}))
    assert read_content_digest(tmp_path) == content_digest({"x": "ab"})
    (tmp_path / "meta" / "dataset.json").write_text("{not json")
    assert read_content_digest(tmp_path) is None


def _run_with(tmp_path, digests: dict) -> None:
    for name, d in digests.items():
        meta = tmp_path / "run" / "data" / name / "meta"
        meta.mkdir(parents=True)
        (meta / "dataset.json").write_text(json.dumps({"n_frames": 3, "content_sha256": d, "files": {}}))
    data_identity.write_data_sets(tmp_path / "run")


def test_compare_with_the_sample(tmp_path):
    _run_with(tmp_path, {"sotif": "a" * 64, "train": "b" * 64, "sweep": "c" * 64})
    table = pd.read_csv(tmp_path / "run" / "tables" / "data_sets.csv", dtype=str)
    assert table["data_set"].tolist() == ["train", "sotif", "sweep"]
    sample = tmp_path / "sample.csv"
    pd.DataFrame({"data_set": ["sotif", "train"], "frames": [3, 3], "content_sha256": ["a" * 64, "d" * 64]}).to_csv(
        sample, index=False)
    lines = data_identity.compare(tmp_path / "run", sample)
    assert "same bytes as the sample's" in lines[1] and lines[1].startswith("data set sotif (3 frames)")
    assert "the sample's is dddddddddddddddd: another data set" in lines[0]
    assert "the sample has no sweep set" in lines[2]
    assert all("no data set digests" in s for s in data_identity.compare(tmp_path / "run", tmp_path / "none.csv"))
    assert data_identity.compare(tmp_path / "empty") == []


def test_the_report_line_names_each_set_once(tmp_path):
    _run_with(tmp_path, {"sotif": "a" * 64, "train": "b" * 64})
    sample = tmp_path / "sample.csv"
    pd.DataFrame({"data_set": ["sotif", "train"], "frames": [3, 3], "content_sha256": ["a" * 64, "d" * 64]}).to_csv(
        sample, index=False)
    assert data_identity.note(tmp_path / "run", sample) == (
        "content SHA-256 of the data sets: train bbbbbbbbbbbbbbbb (3 frames, not the sample's), "
        "sotif aaaaaaaaaaaaaaaa (3 frames, the sample's).")
    assert data_identity.note(tmp_path / "run", tmp_path / "none.csv").endswith(
        "(3 frames); the sample records no data set digests (made before they were recorded).")
    assert data_identity.note(tmp_path / "empty") is None
