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


def compare(run_dir: Path, sample_table: Path = SAMPLE_TABLE) -> list[str]:
    """One sentence per data set of the run: its digest, and whether the sample's set of that name is the same."""
    ours = _read(Path(run_dir) / TABLE)
    if ours is None or ours.empty:
        return []
    sample = _read(sample_table)
    theirs = {} if sample is None else dict(zip(sample["data_set"], sample["content_sha256"]))
    out = []
    for r in ours.itertuples():
        head = f"data set {r.data_set} ({r.frames} frames): content SHA-256 {r.content_sha256[:16]}"
        if sample is None:
            out.append(f"{head}; the sample records no data set digests (made before they were recorded).")
        elif r.data_set not in theirs:
            out.append(f"{head}; the sample has no {r.data_set} set.")
        elif theirs[r.data_set] == r.content_sha256:
            out.append(f"{head}, the same bytes as the sample's.")
        else:
            out.append(f"{head}; the sample's is {theirs[r.data_set][:16]}: another data set (another seed, "
                       f"profile, generator or simulator code), so its numbers are not the sample's draw.")
    return out


def note(run_dir: Path, sample_table: Path = SAMPLE_TABLE) -> str | None:
    """The report's line on the data sets, one clause each (None for a run that recorded none)."""
    ours = _read(Path(run_dir) / TABLE)
    if ours is None or ours.empty:
        return None
    sample = _read(sample_table)
    theirs = {} if sample is None else dict(zip(sample["data_set"], sample["content_sha256"]))
    status = lambda name, digest: ("" if sample is None else ", none in the sample" if name not in theirs
                                   else ", the sample's" if theirs[name] == digest else ", not the sample's")
    parts = [f"{r.data_set} {r.content_sha256[:16]} ({r.frames} frames{status(r.data_set, r.content_sha256)})"
             for r in ours.itertuples()]
    tail = "; the sample records no data set digests (made before they were recorded)" if sample is None else ""
    return f"content SHA-256 of the data sets: {', '.join(parts)}{tail}."
