"""The ``sotif-bench`` command line.

Exit status: 0 on success, 2 on bad input (the message names the file and the problem),
1 on an internal error.
"""
from __future__ import annotations

import argparse
import errno
import os
import sys
import traceback
from pathlib import Path

# Waiting OpenMP threads sleep instead of spinning (set before torch loads its OpenMP runtime):
# with spinning, a 2-core machine with one other busy process ran a PointPillars training step
# in 9.1 s instead of 0.75 s.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

BAD_INPUT = 2
INTERNAL = 1


def _csv(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def _positive_int(text: str) -> int:
    n = int(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return n


def _output_file(text: str) -> Path:
    """A file path to write: not a folder, and no part of its parent path a file (checked before
    any work, so that a long evaluation or export does not fail at its last step)."""
    path = Path(text)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; expected a file path")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise ValueError(f"{parent}: is a file, so {path} cannot be written")
            break
    return path


def cmd_simulate(a) -> int:
    from simulator import generate
    out = generate(Path(a.out), preset=a.preset, frames=a.frames, weathers=_csv(a.weathers) if a.weathers else None,
                   seed=a.seed, workers=a.workers, lidar_model=a.lidar_model, progress=not a.quiet)
    print(f"data set written to {out}")
    return 0


def cmd_train(a) -> int:
    from harness.train import default_workers, train
    workers = a.workers or default_workers(a.model, a.profile, a.device)
    ckpt = train(a.model, Path(a.data), Path(a.out), profile=a.profile, epochs=a.epochs, device=a.device,
                 seed=a.seed, progress=not a.quiet, workers=workers)
    print(f"checkpoint written to {ckpt}")
    return 0


def cmd_export(a) -> int:
    from models.export import export_checkpoint
    from models.zoo import MODEL_NAMES
    if a.model not in MODEL_NAMES:
        raise ValueError(f"unknown model {a.model!r}; expected one of {', '.join(MODEL_NAMES)}")
    out = export_checkpoint(Path(a.checkpoint), _output_file(a.out), expected_model=a.model)
    print(f"ONNX written to {out}")
    return 0


def cmd_predict(a) -> int:
    from harness.infer import predict
    summary = predict(Path(a.onnx), Path(a.data), Path(a.out), split=a.split, runtime=a.runtime,
                      progress=not a.quiet)
    p50 = summary.get("latency_ms_p50")
    print(f"{summary['n_frames']} frames -> {a.out}" + (f"; latency p50 {p50:.1f} ms" if p50 else ""))
    return 0


def cmd_evaluate(a) -> int:
    from harness.evaluate import evaluate, format_table, write_results
    labels, predictions, split = a.labels, a.predictions, a.split
    _output_file(a.output)
    if a.onnx:  # bring your own detector: predict on the data set, then evaluate
        from harness.infer import predict
        if not a.data:
            raise ValueError("--onnx needs --data DIR (a KITTI data set)")
        data = Path(a.data)
        predictions = predictions or str(Path(a.output).parent / f"predictions_{Path(a.onnx).stem}")
        predict(Path(a.onnx), data, Path(predictions), split=a.data_split, runtime=a.runtime, progress=not a.quiet)
        labels = labels or str(data / "training" / "label_2")
        split = split or str(data / "ImageSets" / f"{a.data_split}.txt")
        a.meta = a.meta or (str(data / "meta" / "frames.csv") if a.group_by else None)
    if not labels or not predictions:
        raise ValueError("evaluate needs --labels and --predictions (or --onnx with --data)")
    result = evaluate(labels, predictions, split=split, group_by=a.group_by, meta=a.meta,
                      n_bootstrap=a.bootstrap, seed=a.seed)
    write_results(a.output, result)
    print(format_table(result))
    print(f"results written to {a.output}")
    return 0


def cmd_run(a) -> int:
    from harness.run import run
    out = run(profile=a.profile, models=_csv(a.models) if a.models else None, out=Path(a.out) if a.out else None,
              progress=not a.quiet, runtime=a.runtime, jobs=a.jobs, seeds=a.seeds)
    print(f"report: {out / 'index.html'}")
    return 0


def cmd_report(a) -> int:
    from harness.report import render
    out = render(Path(a.run_dir))
    print(f"report: {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sotif-bench", description=__doc__.splitlines()[0])
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    # --quiet also after the subcommand (``sotif-bench evaluate --quiet ...``)
    quiet = argparse.ArgumentParser(add_help=False)
    quiet.add_argument("--quiet", action="store_true", default=argparse.SUPPRESS, help="no progress bars")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", parents=[quiet],
                       help="simulate the SOTIF test set or training scenes as a KITTI data set")
    s.add_argument("--preset", choices=["sotif", "train"], required=True)
    s.add_argument("--out", required=True)
    s.add_argument("--frames", type=int)
    s.add_argument("--weathers", help="comma-separated CARLA preset names (default: all 21 / the dry ones)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--workers", type=int, default=1)
    s.add_argument("--lidar-model", choices=["physics", "carla"], default="physics")
    s.set_defaults(func=cmd_simulate)

    s = sub.add_parser("train", parents=[quiet], help="train one detector on a KITTI data set")
    s.add_argument("--model", required=True)
    s.add_argument("--data", required=True)
    s.add_argument("--out", required=True)
    s.add_argument("--profile", choices=["tiny", "compact", "kitti"], default="compact")
    s.add_argument("--epochs", type=int)
    s.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--workers", type=_positive_int,
                   help="data-parallel processes, each with its share of the cores and of every batch "
                        "(default: one per core, at most the batch size; 1 = one process)")
    s.set_defaults(func=cmd_train)

    s = sub.add_parser("export", parents=[quiet], help="export a checkpoint to one self-contained ONNX file")
    s.add_argument("--model", required=True)
    s.add_argument("--checkpoint", required=True)
    s.add_argument("--out", required=True)
    s.set_defaults(func=cmd_export)

    s = sub.add_parser("predict", parents=[quiet], help="run an ONNX detector on a data set split, write KITTI results")
    s.add_argument("--onnx", required=True)
    s.add_argument("--data", required=True)
    s.add_argument("--split", default="test")
    s.add_argument("--out", required=True)
    s.add_argument("--runtime", choices=["onnxruntime", "openvino"], default="onnxruntime")
    s.set_defaults(func=cmd_predict)

    s = sub.add_parser("evaluate", parents=[quiet], help="KITTI AP, distance bins, recall and per-group tables")
    s.add_argument("--labels")
    s.add_argument("--predictions")
    s.add_argument("--split", help="ImageSets file listing the frames (default: every label file)")
    s.add_argument("--group-by", help="a column of meta/frames.csv, e.g. weather")
    s.add_argument("--meta", help="meta/frames.csv")
    s.add_argument("--output", required=True, help="results.json")
    s.add_argument("--onnx", help="bring your own detector: predict with this ONNX file first")
    s.add_argument("--data", help="with --onnx: the KITTI data set to run on")
    s.add_argument("--data-split", default="test", help="with --onnx: the split to run (default test)")
    s.add_argument("--runtime", choices=["onnxruntime", "openvino"], default="onnxruntime")
    s.add_argument("--bootstrap", type=_positive_int, default=200, help="bootstrap resamples for 95%% intervals")
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=cmd_evaluate)

    s = sub.add_parser("run", parents=[quiet],
                       help="the whole benchmark: simulate, train, export, predict, evaluate, report")
    s.add_argument("--profile", choices=["quick", "default", "full"], default="default")
    s.add_argument("--models", help="comma-separated model names (default: all available)")
    s.add_argument("--out", help="run directory (default reports/<profile>)")
    s.add_argument("--runtime", choices=["onnxruntime", "openvino"], default="onnxruntime")
    s.add_argument("--jobs", type=_positive_int,
                   help="models trained/exported/predicted at once (default: the profile's, 2; 1 = one after the other)")
    s.add_argument("--seeds", type=_positive_int,
                   help="training draws per model, seeds 0..K-1 (default 1); the tables show their mean and range")
    s.set_defaults(func=cmd_run)

    s = sub.add_parser("report", parents=[quiet], help="re-render a run directory's HTML and Markdown report")
    s.add_argument("run_dir")
    s.set_defaults(func=cmd_report)
    return p


def _bad_input(e: Exception) -> bool:
    """Errors that are the input's, not the program's: ValueErrors (``harness.kitti.KittiError`` and
    ``harness.infer.ContractError`` among them), bad paths, and full or read-only disks."""
    return (isinstance(e, (ValueError, FileNotFoundError, NotADirectoryError, IsADirectoryError, FileExistsError,
                           PermissionError))
            or isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS))


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from harness.malloc import keep_freed_memory
    keep_freed_memory()
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print(f"sotif-bench {args.command}: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    except Exception as e:  # noqa: BLE001 - bad input exits 2, anything else is reported and exits 1
        if _bad_input(e):
            print(f"sotif-bench {args.command}: error: {e}", file=sys.stderr)  # the file and the problem
            return BAD_INPUT
        traceback.print_exc()
        print(f"sotif-bench {args.command}: internal error (see the trace above)", file=sys.stderr)
        return INTERNAL


if __name__ == "__main__":
    sys.exit(main())
