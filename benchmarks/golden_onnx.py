"""The exported ONNX files of the imported published networks against the references' golden boxes.

    python -m benchmarks.golden_onnx [--models pointpillars,second,parta2,pv_rcnn,dv_second,dv_second_car] [--keep DIR]

For each golden file of ``tests/golden`` (``benchmarks/golden_published.py`` and
``benchmarks/golden_parta2.py``, ``benchmarks/golden_pvrcnn.py``, OpenPCDet; ``benchmarks/golden_mmdet3d.py``, MMDetection3D): rebuilds the reference checkpoint from the seeded
rule in the reference's file format, imports it (``sotif-bench import``'s code), exports it
(``sotif-bench export``'s code, one self-contained file), runs the file with onnxruntime on the golden
frame and prints the export time, the number of Car boxes of both and the largest differences of
the box values (yaw modulo 2 pi) and scores, matched in score order. Exits 1 when a count differs
or a box value is off by more than 1e-3 or a score by more than 1e-4 (the done-when of the import).
The kitti exports trace for minutes on a loaded 2-core machine, so CI checks eager torch only
(``tests/models/test_published_golden.py``) and this script the ONNX files.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path


from harness.import_weights import import_checkpoint
from models.export import export_checkpoint, run_onnx
from tests.models import test_published_golden as openpcdet_golden
from tests.models import test_published_golden_mmdet3d as mmdet3d_golden
from tests.models.test_published_golden import car_boxes, differences, load

BOX_TOL, SCORE_TOL = 1e-3, 1e-4
# case -> (source, model, config of the golden file)
CASES = {"pointpillars": ("openpcdet", "pointpillars", ""), "second": ("openpcdet", "second", ""),
         "parta2": ("openpcdet", "parta2", ""), "pv_rcnn": ("openpcdet", "pv_rcnn", ""),
         "dv_second": ("mmdet3d", "dv_second", ""), "dv_second_car": ("mmdet3d", "dv_second", "car")}
REFERENCE_FILE = {"openpcdet": openpcdet_golden.reference_file, "mmdet3d": mmdet3d_golden.reference_file}


def check(case: str, work: Path) -> bool:
    source, model, config = CASES[case]
    g = load(source, model, config)
    REFERENCE_FILE[source](g, work / f"{case}_ref.pth")
    import_checkpoint(work / f"{case}_ref.pth", source, model, work / f"{case}.pt")
    start = time.perf_counter()
    export_checkpoint(work / f"{case}.pt", work / f"{case}.onnx", expected_model=model)
    seconds = time.perf_counter() - start
    boxes, scores = run_onnx(work / f"{case}.onnx", g["points"])[:2]  # (N, 7) boxes, (N,) Car scores
    want_boxes, want_scores = car_boxes(g)
    line = f"{source} {case}: export {seconds:.0f} s; Car boxes ONNX {len(boxes)}, reference {len(want_boxes)}"
    if len(boxes) != len(want_boxes):
        print(line + ": counts differ")
        return False
    diff = differences(boxes, scores, want_boxes, want_scores)
    print(line + f"; max |box value difference| {diff[0]:.2e} (tolerance {BOX_TOL:g}), "
          f"max |score difference| {diff[1]:.2e} (tolerance {SCORE_TOL:g})")
    return diff[0] <= BOX_TOL and diff[1] <= SCORE_TOL


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", default=",".join(CASES), help=f"a comma-separated subset of {', '.join(CASES)}")
    p.add_argument("--keep", type=Path, help="keep the checkpoints and ONNX files in this folder")
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = a.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        ok = [check(case, work) for case in a.models.split(",")]
    return 0 if all(ok) else 1


if __name__ == "__main__":
    sys.exit(main())
