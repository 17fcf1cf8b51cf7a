"""One model's prediction and evaluation on one data set of a run: the stage pair of the SOTIF set
(``harness.run``), the sweep set (``harness.run_space``) and the val set (``harness.valset``).

``predict_<kind><tag>`` runs the model's ONNX file on the set's frames of ``split`` into a folder of KITTI
result files, keyed by the file, the data set and the runtime; ``evaluate_<kind><tag>`` evaluates them
into a results file, keyed by that key, the evaluator version and the predictions' hashes (and the
bootstrap count, except the val set's, which was keyed without it: keys stay as they are, so that a run
resumes with its stages skipped).
"""
from __future__ import annotations

from pathlib import Path

from harness.stages import Stages, file_digest


def predict_evaluate(stages: Stages, cfg, run_dir: Path, tag: str, kind: str, data: Path, data_hash: str,
                     split: str | Path, pred: Path, results: Path, runtime: str, threads: int | None,
                     group_by: tuple[str, ...] = (), bars: bool = True, keyed_bootstrap: bool = True) -> dict:
    """Predict and evaluate ``tag`` on ``data`` (``split``: a split name or an ImageSets file); returns the
    prediction stage's key. ``group_by``: columns of the set's meta/frames.csv; ``bars``: progress bars."""
    from harness.evaluate import EVALUATOR_VERSION, evaluate, write_results
    from harness.infer import predict
    onnx_path = run_dir / "models" / f"{tag}.onnx"
    key = {"onnx": file_digest(onnx_path), "data": data_hash, "runtime": runtime}
    stages.run(f"predict_{kind}{tag}", key, lambda: {"summary": predict(
        onnx_path, data, pred, split=split, runtime=runtime, progress=stages.bars and bars, threads=threads)},
        outputs=[pred])
    split_file = split if isinstance(split, Path) else data / "ImageSets" / f"{split}.txt"
    groups = {"group_by": list(group_by), "meta": data / "meta" / "frames.csv"} if group_by else {}

    def _evaluate() -> dict:
        write_results(results, evaluate(data, pred, split=split_file, **groups, n_bootstrap=cfg.bootstrap,
                                        seed=cfg.seed))
        return {}
    bootstrap = {"bootstrap": cfg.bootstrap} if keyed_bootstrap else {}
    stages.run(f"evaluate_{kind}{tag}", {**key, **bootstrap, "evaluator": EVALUATOR_VERSION,
                                         "predictions": stages.outputs_digest(f"predict_{kind}{tag}")},
               _evaluate, outputs=[results])
    return key
