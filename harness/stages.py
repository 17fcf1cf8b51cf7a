"""Skip-if-current bookkeeping of ``run``'s stages.

Every stage writes a record ``RUN/.stages/<stage>.json``: ``key`` (the hash of its inputs and
config), ``info`` (what it reported) and ``outputs`` (the SHA-256 of each file it wrote, by path
relative to the run folder; a folder output counts every file in it but the hidden bookkeeping
ones); a stage run ``by_stat`` also keeps ``stats``, the size and mtime of its big files. A stage
is skipped only when its key matches and every recorded output is there with its recorded hash.
An output that is missing or was changed since (truncated, emptied, edited) is removed and the
stage runs again, with a line that names the file: a stage resumes from what is left, so a
damaged file is made anew and a sound one is kept. A record that holds no hash of an output (an
older version recorded fewer) runs the stage again too, to record them all.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from harness.core.files import atomic_write_text, sha256_file
from harness.dataset import config_hash
from harness.provenance import machine


BIG_FILE = 1 << 20  # bytes: a stage's record may keep such files' size and mtime, to skip reading them


def file_digest(path: Path) -> str:
    return sha256_file(path)[:16] if Path(path).is_file() else "missing"


def _stat(path: Path) -> list[int]:
    st = path.stat()
    return [st.st_size, st.st_mtime_ns]


def output_files(path: Path) -> list[Path]:
    """``path`` itself, or the files below the folder ``path`` but hidden ones (locks, journals, temp files)."""
    if path.is_file():
        return [path]
    if not path.is_dir():
        return []
    return sorted(p for p in path.rglob("*") if p.is_file()
                  and not any(part.startswith(".") for part in p.relative_to(path).parts))


class Stages:
    """Skip-if-current bookkeeping for the stages of one run directory."""

    def __init__(self, run_dir: Path, progress: bool, bars: bool | None = None, prefix: str = ""):
        self.root = Path(run_dir)
        self.dir = self.root / ".stages"
        self.progress = progress
        self.bars = progress if bars is None else bars  # tqdm bars inside stages (off in parallel jobs)
        self.prefix = prefix

    def record(self, name: str) -> dict | None:
        p = self.dir / f"{name}.json"
        return json.loads(p.read_text()) if p.is_file() else None

    def outputs_digest(self, name: str) -> str:
        """One hash of the files stage ``name`` wrote (for the key of a stage that reads them)."""
        return config_hash((self.record(name) or {}).get("outputs"))

    def hashes(self, outputs) -> dict[str, str]:
        return {p.relative_to(self.root).as_posix(): file_digest(p) for o in outputs for p in output_files(Path(o))}

    def run(self, name: str, key, fn, outputs=(), by_stat: bool = False) -> dict:
        """Run ``fn() -> dict`` unless the stage's record has the same key and its outputs are as it wrote them.

        ``by_stat``: the record also keeps the size and mtime of each output of ``BIG_FILE`` bytes or
        more, and a later check reads such a file only when its mtime changed (one of another size is
        damaged, one as recorded is taken as written): a data set's scans, a GB or more, whose full
        hashing takes seconds from a cold disk cache."""
        key = config_hash(key)
        rec = self.record(name)
        if rec and rec.get("key") == key:
            damaged = self._damaged(rec.get("outputs"), outputs, rec.get("stats", {}))
            if not damaged:
                self._say(f"[skip] {name} (up to date)")
                return rec["info"]
            more = f" (and {len(damaged) - 1} more file(s))" if len(damaged) > 1 else ""
            print(f"{self.prefix}[redo] {name}: {damaged[0]}{more}; running the stage again", file=sys.stderr,
                  flush=True)
        self._say(f"[run ] {name}")
        t0 = time.perf_counter()
        info = fn() or {}
        info = {**info, "seconds": round(time.perf_counter() - t0, 3), "finished": round(time.time(), 3),
                "machine": machine()}
        record = {"key": key, "info": info, "outputs": self.hashes(outputs)}
        if by_stat:
            stats = {rel: _stat(self.root / rel) for rel in record["outputs"]}
            record["stats"] = {rel: st for rel, st in stats.items() if st[0] >= BIG_FILE}
        atomic_write_text(self.dir / f"{name}.json", json.dumps(record, indent=1, default=str))
        self._say(f"[done] {name} in {info['seconds']:.0f} s")
        return info

    def epoch_line(self, model: str):
        """A training's per-epoch progress line with its ETA from the epochs left, where no progress bar
        shows it (a job process beside another); None where the bar does."""
        if not self.progress or self.bars:
            return None

        def say(done: int, epochs: int, per_epoch: float) -> None:
            self._say(f"train {model}: epoch {done}/{epochs}, {per_epoch:.0f} s per epoch, "
                      f"ETA {per_epoch * (epochs - done):.0f} s")
        return say

    def _damaged(self, recorded: dict | None, outputs, stats: dict) -> list[str]:
        """What is wrong with a stage's outputs (empty: all as recorded); a changed file is removed."""
        if recorded is None:
            return ["its record holds no hashes of its outputs (an older version wrote it)"]
        missing = [f"{Path(o).relative_to(self.root)} is missing" for o in outputs if not Path(o).exists()]
        now = {p.relative_to(self.root).as_posix() for o in outputs for p in output_files(Path(o))}
        problems = []
        for rel, expected in recorded.items():
            path = self.root / rel
            if rel not in now:
                problems.append(f"{rel} is missing")
            elif not as_recorded(path, expected, stats.get(rel)):
                problems.append(f"{rel} is not the file the stage wrote (now {path.stat().st_size} bytes)")
                path.unlink()
        return problems + self._uncovered(recorded, outputs, now) or missing

    def _uncovered(self, recorded: dict, outputs, now: set[str]) -> list[str]:
        """The outputs that hold files now but none in the record: a version that recorded fewer of
        the stage's outputs wrote it (e.g. a data set's ``meta/dataset.json`` alone)."""
        def under(rel: str, paths) -> bool:
            return any(p == rel or p.startswith(rel + "/") for p in paths)
        rels = [Path(o).relative_to(self.root).as_posix() for o in outputs]
        bare = [rel for rel in rels if under(rel, now) and not under(rel, recorded)]
        if not bare:
            return []
        more = f" and {len(bare) - 1} more output(s)" if len(bare) > 1 else ""
        return [f"its record holds no hashes of {bare[0]}{more} (an older version wrote it)"]

    def _say(self, msg: str) -> None:
        if self.progress:
            print(self.prefix + msg, flush=True)


def as_recorded(path: Path, digest: str, stat: list[int] | None) -> bool:
    """Whether ``path`` is the file whose digest was recorded: read and hashed, unless its recorded
    ``stat`` (size, mtime) tells without reading it."""
    if stat is not None:
        now = _stat(path)
        if now[0] != stat[0]:
            return False
        if now == stat:
            return True
    return file_digest(path) == digest
