"""Which data sets a run was made on: the content digest of each (simulator.dataset.content_digest, in
the set's meta/dataset.json), written to tables/data_sets.csv and compared with the tracked sample's
table, so that a run on another CPU, seed or generator says whether its data are the sample's."""
from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

from harness.core.files import atomic_write_text
from harness.provenance import ROOT
from simulator.dataset import read_content_digest

TABLE = Path("tables") / "data_sets.csv"
SAMPLE_TABLE = ROOT / "reports" / "sample" / TABLE
SETS = ("train", "val", "sotif", "sweep")  # the run's data/<name> folders, in the order a run makes them
COLUMNS = ["data_set", "frames", "content_sha256"]


def data_sets(run_dir: Path) -> pd.DataFrame:
    """One row per data set of the run (data/<name>/meta/dataset.json readable): name, frames, digest."""
    rows = []
    for name in SETS:
        root = Path(run_dir) / "data" / name
        digest = read_content_digest(root)
        if digest is not None:
            frames = json.loads((root / "meta" / "dataset.json").read_text()).get("n_frames")
            rows.append({"data_set": name, "frames": frames, "content_sha256": digest})
    return pd.DataFrame(rows, columns=COLUMNS)


def write_data_sets(run_dir: Path) -> Path:
    out = Path(run_dir) / TABLE
    atomic_write_text(out, data_sets(run_dir).to_csv(index=False, lineterminator="\n"))
    return out


def _read(path: Path) -> pd.DataFrame | None:
    try:
        df = pd.read_csv(path, dtype=str)
    except (OSError, ValueError):
        return None
    return df if set(COLUMNS) <= set(df.columns) else None


def _matched(run_dir: Path, sample_table: Path) -> tuple[list[tuple], bool]:
    """The run's data sets as (name, frames, digest, the sample's digest of that name or None), and whether
    the sample records digests at all."""
    ours, sample = _read(Path(run_dir) / TABLE), _read(sample_table)
    theirs = {} if sample is None else dict(zip(sample["data_set"], sample["content_sha256"]))
    rows = [] if ours is None else [(r.data_set, r.frames, r.content_sha256, theirs.get(r.data_set))
                                    for r in ours.itertuples()]
    return rows, sample is not None


def compare(run_dir: Path, sample_table: Path = SAMPLE_TABLE) -> list[str]:
    """One sentence per data set of the run: its digest, and whether the sample's set of that name is the same."""
    rows, recorded = _matched(run_dir, sample_table)
    out = []
    for name, frames, digest, theirs in rows:
        head = f"data set {name} ({frames} frames): content SHA-256 {digest[:16]}"
        if not recorded:
            out.append(f"{head}; the sample records no data set digests (made before they were recorded).")
        elif theirs is None:
            out.append(f"{head}; the sample has no {name} set.")
        elif theirs == digest:
            out.append(f"{head}, the same bytes as the sample's.")
        else:
            out.append(f"{head}; the sample's is {theirs[:16]}: another data set (another seed, "
                       f"profile, generator or simulator code), so its numbers are not the sample's draw.")
    return out


def note(run_dir: Path, sample_table: Path = SAMPLE_TABLE) -> str | None:
    """The report's line on the data sets, one clause each (None for a run that recorded none)."""
    rows, recorded = _matched(run_dir, sample_table)
    if not rows:
        return None
    status = lambda digest, theirs: ("" if not recorded else ", none in the sample" if theirs is None
                                     else ", the sample's" if theirs == digest else ", not the sample's")
    parts = [f"{name} {digest[:16]} ({frames} frames{status(digest, theirs)})" for name, frames, digest, theirs in rows]
    tail = "" if recorded else "; the sample records no data set digests (made before they were recorded)"
    return f"content SHA-256 of the data sets: {', '.join(parts)}{tail}."
