"""Publish a run's report as the repository's sample (``sotif-bench report RUN --sample reports/sample``).

The sample is what a reader needs to see a run's results without making one: ``report.md``,
``index.html``, ``tables/*.csv`` and ``figures/*.png`` (a few MB; no ONNX files, checkpoints
or predictions). The copy is built in a temp folder beside the destination and then swapped in,
so a failed copy leaves the previous sample as it was.
"""
from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from harness.kitti import KittiError
from harness.tables import _read_json

SAMPLE_PATTERNS = ("report.md", "index.html", "tables/*.csv", "figures/*.png")


def sample_files(run_dir: Path) -> list[Path]:
    """The files of ``run_dir`` that make up a sample, relative to it, in a stable order."""
    return sorted(p.relative_to(run_dir) for pattern in SAMPLE_PATTERNS for p in run_dir.glob(pattern) if p.is_file())


def publish_sample(run_dir, dest) -> Path:
    """Copy the rendered report of ``run_dir`` into ``dest`` (replacing what was there); returns ``dest``.

    A quick-profile run is refused: its tiny models' numbers mean nothing."""
    run_dir, dest = Path(run_dir), Path(dest)
    summary_path = run_dir / "results.json"
    if _read_json(summary_path).get("profile") == "quick":
        raise KittiError(summary_path, "a quick-profile run (a smoke run: numbers meaningless) cannot be the sample")
    files = sample_files(run_dir)
    for needed in ("report.md", "index.html"):
        if Path(needed) not in files:
            raise KittiError(run_dir / needed, "file not found (render the report first)")
    if dest.resolve() == run_dir.resolve() or run_dir.resolve() in dest.resolve().parents:
        raise ValueError(f"{dest}: the sample folder must lie outside the run folder {run_dir}")
    dest.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=dest.parent, prefix=f".{dest.name}.", suffix=".tmp"))
    old = None
    try:
        for rel in files:
            (staging / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(run_dir / rel, staging / rel)
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
