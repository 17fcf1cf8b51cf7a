"""Publish a run's report as the repository's sample (``sotif-bench report RUN --sample reports/sample``).

The sample is what a reader needs to see a run's results without making one: ``report.md``,
``index.html``, ``tables/*.csv`` and ``figures/*.png`` (a few MB; no ONNX files, checkpoints
or predictions). The copy is built in a temp folder beside the destination and then swapped in,
so a failed copy leaves the previous sample as it was.
"""
from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

from harness.core.kitti import KittiError
from harness.tables import read_json_object

SAMPLE_PATTERNS = ("report.md", "index.html", "tables/*.csv", "figures/*.png")
SAMPLE_DIRS = {Path(p).parent for p in SAMPLE_PATTERNS} - {Path(".")}
MANIFEST = ".sample.json"  # the files a sample holds, written with it: what replacing it may delete


def sample_files(run_dir: Path) -> list[Path]:
    """The files of ``run_dir`` that make up a sample, relative to it, in a stable order."""
    return sorted(p.relative_to(run_dir) for pattern in SAMPLE_PATTERNS for p in run_dir.glob(pattern) if p.is_file())


def _foreign_entry(folder: Path, new_files: list[Path]) -> Path | None:
    """The first entry of ``folder`` that replacing it with a sample of ``new_files`` would delete
    without having written it (a symbolic link counts as foreign), or None when ``folder`` is empty
    or a previous sample. A sample lists its files in ``MANIFEST``; a folder without one (published
    before it existed) passes only when it holds a report.md and an index.html and nothing but
    files the new sample writes again."""
    entries = sorted(folder.rglob("*"))
    if not entries:
        return None
    try:
        listed = json.loads((folder / MANIFEST).read_text())["files"]
        expected = {Path(f) for f in listed} | {Path(MANIFEST)}
    except (OSError, ValueError, KeyError, TypeError):
        if not ((folder / "report.md").is_file() and (folder / "index.html").is_file()):
            return entries[0].relative_to(folder)
        expected = set(new_files)
    for p in entries:
        rel = p.relative_to(folder)
        if p.is_symlink() or not (rel in expected or rel in SAMPLE_DIRS and p.is_dir()):
            return rel
    return None


def check_destination(run_dir, dest) -> None:
    """Raise ValueError unless ``dest`` may become ``run_dir``'s sample: a new folder, an empty one or a previous
    sample, neither holding the run nor inside it."""
    run_dir, dest = Path(run_dir), Path(dest)
    run, target = run_dir.resolve(), dest.resolve()
    if dest.is_symlink():
        raise ValueError(f"{dest}: is a symbolic link; name the sample folder itself")
    if dest.exists() and not dest.is_dir():
        raise ValueError(f"{dest}: is a file, not a folder; the sample must go to a folder of its own")
    if target == run or target in run.parents:
        raise ValueError(f"{dest}: holds the run folder {run_dir}; publishing the sample there would delete the run")
    if run in target.parents:
        raise ValueError(f"{dest}: the sample folder must lie outside the run folder {run_dir}")
    foreign = _foreign_entry(dest, sample_files(run_dir)) if dest.is_dir() else None
    if foreign is not None:
        raise ValueError(f"{dest}: is not empty and not a previous sample (it holds {foreign}, which a sample "
                         "does not); choose a new or empty folder")


def publish_sample(run_dir, dest) -> Path:
    """Copy the rendered report of ``run_dir`` into ``dest`` (replacing a previous sample there); returns ``dest``.

    A quick-profile run is refused: its tiny models' numbers mean nothing; so is a ``dest`` that
    ``check_destination`` refuses."""
    run_dir, dest = Path(run_dir), Path(dest)
    summary_path = run_dir / "results.json"
    if read_json_object(summary_path).get("profile") == "quick":
        raise KittiError(summary_path, "a quick-profile run (a smoke run: numbers meaningless) cannot be the sample")
    files = sample_files(run_dir)
    for needed in ("report.md", "index.html"):
        if Path(needed) not in files:
            raise KittiError(run_dir / needed, "file not found (render the report first)")
    check_destination(run_dir, dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=dest.parent, prefix=f".{dest.name}.", suffix=".tmp"))
    old = None
    try:
        for rel in files:
            (staging / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(run_dir / rel, staging / rel)
        (staging / MANIFEST).write_text(json.dumps({"files": [str(f) for f in files]}, indent=1) + "\n")
        if dest.exists():
            old = dest.rename(dest.parent / f"{staging.name}.old")
        staging.rename(dest)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        if old is not None and not dest.exists():
            old.rename(dest)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return dest
