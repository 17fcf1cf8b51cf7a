"""Time the check a rerun of ``run`` makes of a run's data sets before it skips the simulate stages:
every byte hashed, against the record's size and mtime of the scans (``Stages.run(by_stat=True)``),
each from the page cache and after dropping the files from it (``posix_fadvise``; a disk or host
cache below may still hold them).

    python benchmarks/bench_verify.py RUN    # a finished run folder, e.g. reports/default
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from harness.run import DATA_PARTS
from harness.stages import Stages, as_recorded, output_files


def drop_from_cache(files: list[Path]) -> None:
    for path in files:
        fd = os.open(path, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    args = ap.parse_args()
    stages = Stages(args.run, progress=False)
    for preset in ("train", "sotif"):
        rec = stages.record(f"simulate_{preset}")
        outputs = [args.run / "data" / preset / part for part in DATA_PARTS]
        files = [p for o in outputs for p in output_files(o)]
        size = sum(p.stat().st_size for p in files) / 2**30
        print(f"{preset}: {len(files)} files, {size:.2f} GiB, {len(rec.get('stats', {}))} checked by size and mtime")
        for label, stats in (("every byte hashed", {}), ("scans by size and mtime", rec.get("stats", {}))):
            for cold in (False, True):
                if cold:
                    drop_from_cache(files)
                t0 = time.perf_counter()
                sound = all(as_recorded(args.run / rel, digest, stats.get(rel))
                            for rel, digest in rec["outputs"].items())
                where = "after dropping the cache" if cold else "from the page cache"
                print(f"  {label}, {where}: {time.perf_counter() - t0:.2f} s{'' if sound else ' (damaged)'}")


if __name__ == "__main__":
    main()
