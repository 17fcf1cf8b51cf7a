"""The ``sotif-bench`` command line.

Exit status: 0 on success, 2 on bad input (the message names the file and the problem),
1 on an internal error.
"""
from __future__ import annotations

import argparse
import errno
import math
import os
import sys
import traceback
from dataclasses import replace
from pathlib import Path

# Waiting OpenMP threads sleep instead of spinning (set before torch loads its OpenMP runtime):
# with spinning, a 2-core machine with one other busy process ran a PointPillars training step
# in 9.1 s instead of 0.75 s.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from harness.cli_help import CommandParser, command_text

BAD_INPUT = 2
INTERNAL = 1
FORCE_HELP = "replace the output even when it is an input or a file of another kind (refused otherwise)"


def _csv(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def _positive_int(text: str) -> int:
    n = int(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return n


def _nonnegative_int(text: str) -> int:
    n = int(text)
    if n < 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer, got {text!r}")
    return n


def _path(text: str) -> str:
    """An output path as given: refused when empty (``Path("")`` is the current folder)."""
    if not text:
        raise argparse.ArgumentTypeError("expected a path, got an empty string")
    return text


def _file_above(path: Path) -> Path | None:
    """The nearest existing parent of ``path`` when it is a file (so ``path`` cannot be made), else None."""
    parent = next((p for p in path.parents if p.exists()), None)
    return parent if parent is not None and not parent.is_dir() else None


def _folder(text: str) -> str:
    """An output folder: a path that is not a file and has no file among its parents."""
    path = Path(_path(text))
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{path}: is a file, expected a folder")
    if (above := _file_above(path)) is not None:
        raise argparse.ArgumentTypeError(f"{above}: is a file, so the folder {path} cannot be made")
    return text


def _output_file(text: str) -> Path:
    """A file path to write: not a folder, and no part of its parent path a file (checked before
    any work, so that a long evaluation or export does not fail at its last step)."""
    path = Path(text)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; expected a file path")
    if (above := _file_above(path)) is not None:
        raise ValueError(f"{above}: is a file, so {path} cannot be written")
    return path


def _nonempty_csv(text: str | None, option: str) -> list[str] | None:
    """A comma-separated list option: None when not given, an error when given but empty."""
    if text is None:
        return None
    items = _csv(text)
    if not items:
        raise ValueError(f"{option} is empty; leave it out to use the default, or name at least one")
    return items


def _split(split: str, root: Path | None) -> str | Path:
    """``--split`` as ``predict`` and ``evaluate`` both read it: the name of a split of the data set
    ``root`` (``root/ImageSets/NAME.txt``), else the path of an ImageSets file."""
    if root is not None and (root / "ImageSets" / f"{split}.txt").is_file():
        return split
    if Path(split).is_file():
        return Path(split)
    if root is not None and "/" not in split and (root / "ImageSets" / split).is_file():  # "val.txt"
        return root / "ImageSets" / split
    if "/" in split or split.endswith(".txt"):  # meant as a file, not as a split name
        raise ValueError(f"--split {split}: file not found" if not Path(split).exists()
                         else f"--split {split}: not a file (an ImageSets file lists one frame id per line)")
    where = f"a split of {root} (no {root / 'ImageSets' / f'{split}.txt'})" if root is not None else "a split name"
    raise ValueError(f"--split {split}: neither {where} nor an ImageSets file")


def _data_root(labels: str) -> Path:
    """The data set root of a labels folder (``<root>/training/label_2``, or the root itself)."""
    path = Path(labels)
    return path.parent.parent if path.name == "label_2" else path


def _model_name(name: str) -> str:
    """--model as models.zoo spells it (any case), or a ValueError with a suggestion and the valid names."""
    from harness.names import resolve_names
    from models.zoo import MODEL_NAMES
    return resolve_names([name], MODEL_NAMES, "--model", "model")[0]


def cmd_simulate(a) -> int:
    from simulator import generate
    from harness.names import resolve_names
    from simulator.weather import WEATHER_PRESETS
    weathers = _nonempty_csv(a.weathers, "--weathers")
    weathers = weathers and resolve_names(weathers, list(WEATHER_PRESETS), "--weathers", "weather preset")
    probes = _probes(a)
    out = generate(Path(a.out), preset=a.preset, frames=a.frames, weathers=weathers,
                   seed=a.seed, workers=a.workers, lidar_model=a.lidar_model, progress=not a.quiet, force=a.force,
                   instances=1 if a.instances is None else a.instances, probes=probes)
    from simulator.dataset import read_content_digest
    print(f"data set written to {out} (content SHA-256 {read_content_digest(out)}, in meta/dataset.json)")
    return 0


PROBE_OPTIONS = ("axis", "values", "scenarios", "noise_seeds")  # simulate's options of the bounds preset
# simulator.bounds's AXES and reference scenarios, spelled here so that building the parser imports no simulator
BOUNDS_AXES = ("rain", "fog", "water", "reflectance")
BOUNDS_SCENARIOS = "90-60 or 120-60 km/h, sedan or suv, silver or black: e.g. 90-60_sedan_silver"


def _probes(a):
    """The probes of ``simulate --preset bounds`` (every scenario x value x noise seed), None for other presets;
    ValueError naming the option that is missing, malformed or given with another preset."""
    from simulator.bounds import REFERENCES, Probe, check_probes
    given = [f"--{n.replace('_', '-')}" for n in PROBE_OPTIONS if getattr(a, n) is not None]
    if a.preset != "bounds":
        if given:
            raise ValueError(f"{given[0]} goes with --preset bounds only")
        return None
    for name in ("axis", "values"):
        if getattr(a, name) is None:
            raise ValueError(f"--preset bounds needs --{name}")
    from harness.names import resolve_names
    values = [_float_item(v, "--values") for v in _nonempty_csv(a.values, "--values")]
    scenarios = list(REFERENCES) if a.scenarios in (None, "all") else resolve_names(
        _nonempty_csv(a.scenarios, "--scenarios"), list(REFERENCES), "--scenarios", "reference scenario")
    seeds = [0] if a.noise_seeds is None else [_int_item(v, "--noise-seeds")
                                                for v in _nonempty_csv(a.noise_seeds, "--noise-seeds")]
    return check_probes(Probe(s, a.axis, v, k) for s in scenarios for v in values for k in seeds)


def _float_item(text: str, option: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{option}: {text!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"{option}: {text!r} is not a finite number")
    return value


def _int_item(text: str, option: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"{option}: {text!r} is not an integer") from None


def cmd_train(a) -> int:
    from harness.train import default_workers, train
    from models.zoo import resolve
    recipe = resolve(_model_name(a.model), a.profile, warm=a.init_from is not None)
    if a.ema is not None:
        if not 0.0 <= a.ema < 1.0:
            raise ValueError(f"--ema {a.ema:g}: the average's decay per step lies in [0, 1) (0: no average)")
        recipe = replace(recipe, schedule=replace(recipe.schedule, ema=a.ema))
    if a.amp:
        recipe = replace(recipe, schedule=replace(recipe.schedule, amp=a.amp))
    workers = a.workers or default_workers(recipe, device=a.device)
    ckpt = train(recipe, Path(a.data), Path(a.out), epochs=a.epochs, device=a.device,
                 seed=a.seed, progress=not a.quiet, workers=workers, force=a.force, init_from=a.init_from)
    print(f"checkpoint written to {ckpt}")
    return 0


def cmd_export(a) -> int:
    from models.export import export_checkpoint
    a.model = _model_name(a.model)
    from harness.protect import foreign_onnx, refuse_overwrite
    out = _output_file(a.out)
    refuse_overwrite(out, "an ONNX model", {"--checkpoint": a.checkpoint}, foreign_onnx, a.force)
    say = None if a.quiet else (lambda msg: print(msg, flush=True))
    out = export_checkpoint(Path(a.checkpoint), out, expected_model=a.model, say=say)
    print(f"ONNX written to {out}")
    return 0


def cmd_import(a) -> int:
    from harness.import_weights import import_checkpoint
    from harness.protect import refuse_overwrite
    out = _output_file(a.out)
    refuse_overwrite(out, "a checkpoint", {"--checkpoint": a.checkpoint}, None, a.force)
    info = import_checkpoint(Path(a.checkpoint), a.source, a.model, out)
    print(f"{a.model} kitti checkpoint written to {out} ({info['config']}, classes {', '.join(info['classes'])}; "
          "Car boxes are reported)")
    return 0


def cmd_predict(a) -> int:
    from harness.infer import predict
    summary = predict(Path(a.onnx), Path(a.data), Path(a.out), split=_split(a.split, Path(a.data)), runtime=a.runtime,
                      progress=not a.quiet)
    p50 = summary.get("latency_ms_p50")
    print(f"{summary['n_frames']} frames -> {a.out}" + (f"; latency p50 {p50:.1f} ms" if p50 else ""))
    return 0


def cmd_evaluate(a) -> int:
    from harness.evaluate import evaluate, format_table, label_dir, write_results
    from harness.protect import foreign_results, refuse_overwrite
    if a.split and a.data_split and a.split != a.data_split:
        raise ValueError(f"--split {a.split} and --data-split {a.data_split} disagree (--data-split is the former "
                         "spelling of --split); give one")
    labels, predictions, split = a.labels, a.predictions, a.split or a.data_split  # --data-split: the old spelling
    _output_file(a.output)
    data = None
    if a.onnx:  # bring your own detector: predict on the data set, then evaluate
        if not a.data:
            raise ValueError("--onnx needs --data DIR (a KITTI data set)")
        data = Path(a.data)
        split = _split(split or "test", data)
        predictions = predictions or str(Path(a.output).parent / f"predictions_{Path(a.onnx).stem}")
        labels = labels or str(data / "training" / "label_2")
        a.meta = a.meta or (str(data / "meta" / "frames.csv") if a.group_by else None)
    if not labels or not predictions:
        raise ValueError("evaluate needs --labels and --predictions (or --onnx with --data)")
    root = _data_root(labels)
    if a.group_by and not a.meta and (root / "meta" / "frames.csv").is_file():
        a.meta = str(root / "meta" / "frames.csv")  # the labels' own data set's table
    if split is not None:  # a split name or file, as a file
        split = _split(split, root) if isinstance(split, str) else split
        split = root / "ImageSets" / f"{split}.txt" if isinstance(split, str) else split
    inputs = {"--labels": label_dir(labels), "--predictions": predictions, "--split": split, "--meta": a.meta,
              "--onnx": a.onnx}
    refuse_overwrite(a.output, "results JSON", inputs, foreign_results, a.force)
    if a.onnx:
        from harness.infer import predict
        predict(Path(a.onnx), data, Path(predictions), split=split, runtime=a.runtime, progress=not a.quiet)
    result = evaluate(labels, predictions, split=split, group_by=a.group_by, meta=a.meta,
                      n_bootstrap=a.bootstrap, seed=a.seed)
    write_results(a.output, result)
    print(format_table(result))
    print(f"results written to {a.output}")
    return 0


def cmd_run(a) -> int:
    from harness.run import run
    models = _nonempty_csv(a.models, "--models")
    if models == ["none"]:  # only the imported models of --checkpoints
        models = []
    elif models:
        from harness.names import resolve_names
        from models.zoo import MODEL_NAMES
        models = resolve_names(models, MODEL_NAMES, "--models", "model")
    out = run(profile=a.profile, models=models, out=Path(a.out) if a.out else None,
              progress=not a.quiet, runtime=a.runtime, jobs=a.jobs, seeds=a.seeds, lidar_model=a.lidar_model,
              warm_start=a.warm_start, instances=a.instances, sweep_instances=a.sweep_instances,
              checkpoints=a.checkpoints)
    print(f"report: {out / 'index.html'}")
    return 0


def cmd_verdict(a) -> int:
    from harness.sotif import operating_threshold
    from harness.verdict import REACTIONS, Rule, verdict, write_verdict
    out = _output_file(a.output)
    if a.latency_ms is not None and not a.latency_ms >= 0:
        raise ValueError(f"--latency-ms {a.latency_ms:g}: a latency must be >= 0 ms")
    if a.threshold is not None and not 0.0 <= a.threshold <= 1.0:
        raise ValueError(f"--threshold {a.threshold:g}: a score threshold lies in [0, 1]")
    from harness.protect import refuse_overwrite
    data, predictions = Path(a.data), Path(a.predictions)
    refuse_overwrite(out, "a verdict", {"--data": data, "--predictions": predictions}, None, a.force)
    threshold, source = (a.threshold, "given") if a.threshold is not None else operating_threshold(data, predictions)
    result = verdict(data, predictions, threshold, latency_ms=a.latency_ms, split=a.split,
                     rule=Rule(reaction_s=REACTIONS[a.reaction]), model=a.model)
    result["threshold_source"] = source
    write_verdict(out, result)
    for row in result["summary"]:
        print(f"{row['verdict']:>10} {row['body_class']:<28} {row['n_pass']}/{row['n']} preventable instances passed "
              f"({row['n_unpreventable']} unpreventable)")
    print(f"verdict written to {out}")
    return 0


def cmd_report(a) -> int:
    if a.run_dir is None and not a.docs:
        raise ValueError("give a run folder (reports/NAME) to render, or --docs to write the documents from the sample")
    if a.run_dir is not None:
        from harness.provenance import check_run
        from harness.report import render
        from harness.sample import check_destination, publish_sample
        if a.sample:
            check_destination(a.run_dir, a.sample)  # before rendering: a refused DIR leaves everything as it was
        out = render(Path(a.run_dir))
        print(f"report: {out}")
        print(f"code: {check_run(a.run_dir)}")
        if a.sample:
            print(f"sample: {publish_sample(Path(a.run_dir), Path(a.sample))}")
    if a.docs:
        from harness.sample_docs import report_docs
        return report_docs(sample=Path(a.sample) if a.sample else None)
    return 0


SPLIT_HELP = "a split name of the data set (test, val, train: ImageSets/NAME.txt) or an ImageSets file"
RUNTIMES = ["onnxruntime", "openvino"]


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("sotif-bench")
    except PackageNotFoundError:  # run from a source tree that is not installed
        return "unknown (not installed)"


def _add_simulate(sub, quiet) -> None:
    s = sub.add_parser("simulate", parents=[quiet], **command_text("simulate"),
                       help="simulate the SOTIF test set or training scenes as a KITTI data set")
    s.add_argument("--preset", choices=["sotif", "train", "sweep", "bounds"], required=True,
                   help="sotif: the cut-out scenario under every weather; train: randomised training scenes; "
                        "sweep: scenario instances under continuous rain, fog and road water; bounds: a controlled "
                        "sweep, reference scenarios held fixed and one axis varied (--axis, --values)")
    s.add_argument("--instances", type=int,
                   help="scenario instances per weather (sweep: in all) from a seeded space-filling design; 1 with "
                        "sotif is the study's protocol, byte for byte (default 1)")
    s.add_argument("--out", required=True, type=_folder,
                   help="the data set folder to write (resumed if it holds a partial one of the same options)")
    s.add_argument("--force", action="store_true",
                   help="write the data set over what the folder holds: a data set of other options, or other "
                        "files (refused otherwise)")
    s.add_argument("--frames", type=int, help="number of frames (default: 547 for sotif, 400 for train)")
    s.add_argument("--weathers", help="comma-separated CARLA preset names, any case, as listed above "
                                      "(default: all 21 / the dry ones)")
    s.add_argument("--seed", type=_nonnegative_int, default=0,
                   help="random seed; the same seed gives the same bytes (default 0)")
    s.add_argument("--workers", type=int, default=1, help="processes simulating frames at once (default 1)")
    s.add_argument("--lidar-model", choices=["physics", "carla"], default="physics",
                   help="physics: weather changes the LiDAR; carla: CARLA's weather-blind LiDAR (default physics)")
    s.add_argument("--axis", choices=BOUNDS_AXES,
                   help="bounds: the axis varied (rain mm/h, fog visibility m, road water share, the slow car's "
                        "reflectance at 905 nm; ranges in docs/simulator.md)")
    s.add_argument("--values", help="bounds: comma-separated values of the axis, one instance each per scenario "
                                    "and noise seed")
    s.add_argument("--scenarios", help="bounds: comma-separated reference scenarios KINEMATICS_BODY_PAINT (" +
                                       BOUNDS_SCENARIOS + "), or all (default)")
    s.add_argument("--noise-seeds", help="bounds: comma-separated noise seeds, each redrawing the sensor noise, "
                                         "the rain and fog returns and the spray (default 0)")
    s.set_defaults(func=cmd_simulate)


def _add_train(sub, quiet) -> None:
    s = sub.add_parser("train", parents=[quiet], help="train one detector on a KITTI data set", **command_text("train"))
    s.add_argument("--model", required=True, help="model name, one of those listed above")
    s.add_argument("--data", required=True, help="KITTI data set folder with ImageSets/train.txt")
    s.add_argument("--out", required=True, type=_folder, help="folder for checkpoint.pt (a training there resumes)")
    s.add_argument("--force", action="store_true", help=FORCE_HELP)
    s.add_argument("--profile", choices=["tiny", "compact", "kitti"], default="compact",
                   help="model size: tiny (tests), compact (CPU, default), kitti (the references' settings, GPU)")
    s.add_argument("--epochs", type=int, help="epochs (default: the profile's schedule for the model)")
    s.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help="where to train (default cpu)")
    s.add_argument("--seed", type=_nonnegative_int, default=0,
                   help="random seed of weights, order and augmentation (default 0)")
    s.add_argument("--workers", type=_positive_int,
                   help="data-parallel processes, each with its share of the cores and of every batch "
                        "(default: one per core, at most the batch size; 1 = one process)")
    s.add_argument("--init-from", metavar="CKPT",
                   help="start from the weights of this checkpoint that fit by name and shape: a sibling's "
                        "first stage, e.g. SECOND's for pv_rcnn or parta2, DV-SECOND's for mvx_net")
    s.add_argument("--ema", type=float, metavar="DECAY",
                   help="keep an exponential moving average of the weights with this decay per step (e.g. "
                        "0.999; warmed up as TensorFlow's) and checkpoint, evaluate and export it (default: the "
                        "profile's, none)")
    s.add_argument("--amp", choices=["bf16"],
                   help="run each step's forward pass and loss in bfloat16 (CPU autocast; the weights, optimizer, "
                        "checkpoint, validation and export stay float32), where the CPU has native bf16 (AMX / "
                        "AVX512-BF16); elsewhere refused with exit 2, naming the CPU flags missing (default: the "
                        "profile's, float32)")
    s.set_defaults(func=cmd_train)


def _add_export(sub, quiet) -> None:
    s = sub.add_parser("export", parents=[quiet], help="export a checkpoint to one self-contained ONNX file",
                       **command_text("export"))
    s.add_argument("--model", required=True, help="the model name the checkpoint was trained as (listed above)")
    s.add_argument("--checkpoint", required=True, help="checkpoint.pt written by train")
    s.add_argument("--out", required=True, type=_path, help="the ONNX file to write")
    s.add_argument("--force", action="store_true", help=FORCE_HELP)
    s.set_defaults(func=cmd_export)


IMPORT_EXAMPLE = """example:
  sotif-bench import --from openpcdet --model pointpillars --checkpoint pointpillar_7728.pth --out pp.pt
  sotif-bench export --model pointpillars --checkpoint pp.pt --out pointpillars.onnx

published networks: --from openpcdet --model pointpillars (tools/cfgs/kitti_models/pointpillar.yaml),
--from openpcdet --model second (second.yaml), --from openpcdet --model parta2 (PartA2.yaml),
--from openpcdet --model pv_rcnn (pv_rcnn.yaml),
--from mmdet3d --model dv_second (configs/dynamic_voxelization/second_dv_secfpn_8xb2-cosine-80e_kitti-3d-3class.py)"""


def _add_import(sub, quiet) -> None:
    s = sub.add_parser("import", parents=[quiet], epilog=IMPORT_EXAMPLE,
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       help="turn a published OpenPCDet / MMDetection3D checkpoint into a kitti-profile checkpoint",
                       description="Read a published checkpoint without running code from it (tensors only), map "
                                   "every tensor onto the model's kitti profile (the published network) and write "
                                   "a checkpoint that export turns into one ONNX file. A file of another model or "
                                   "version, or with missing, extra or misshapen tensors, exits 2 listing them "
                                   "and writes nothing.")
    s.add_argument("--from", dest="source", required=True, choices=("openpcdet", "mmdet3d"),
                   help="the code base that wrote the checkpoint")
    s.add_argument("--model", required=True, help="pointpillars, second, parta2 or pv_rcnn (openpcdet), dv_second (mmdet3d)")
    s.add_argument("--checkpoint", required=True, help="the published .pth file")
    s.add_argument("--out", required=True, type=_path, help="the checkpoint (.pt) to write")
    s.add_argument("--force", action="store_true", help=FORCE_HELP)
    s.set_defaults(func=cmd_import)


def _add_predict(sub, quiet) -> None:
    s = sub.add_parser("predict", parents=[quiet], help="run an ONNX detector on a data set split, write KITTI results",
                       **command_text("predict"))
    s.add_argument("--onnx", required=True, help="ONNX file following the contract (README)")
    s.add_argument("--data", required=True, help="KITTI data set folder")
    s.add_argument("--split", default="test", help=SPLIT_HELP + " (default test)")
    s.add_argument("--out", required=True, type=_folder, help="folder for the KITTI result files (a run there resumes)")
    s.add_argument("--runtime", choices=RUNTIMES, default="onnxruntime", help="inference runtime (default onnxruntime)")
    s.set_defaults(func=cmd_predict)


def _add_evaluate(sub, quiet) -> None:
    s = sub.add_parser("evaluate", parents=[quiet], help="KITTI AP, distance bins, recall and per-group tables",
                       **command_text("evaluate"))
    s.add_argument("--labels", help="label folder (DATA/training/label_2) or data set folder")
    s.add_argument("--predictions", help="folder of KITTI result files (from predict)")
    s.add_argument("--split", help=SPLIT_HELP + " (default: every label file; with --onnx: test)")
    s.add_argument("--group-by", help="a column of meta/frames.csv, e.g. weather (a numeric one with more than "
                                      "10 values, a swept condition, groups by quantile bins)")
    s.add_argument("--meta", help="with --group-by: the data set's meta/frames.csv (default: the one "
                   "beside the labels, <root>/meta/frames.csv, when there is one)")
    s.add_argument("--output", required=True, type=_path, help="results.json to write")
    s.add_argument("--force", action="store_true", help=FORCE_HELP)
    s.add_argument("--onnx", help="bring your own detector: predict with this ONNX file first")
    s.add_argument("--data", help="with --onnx: the KITTI data set to run on")
    s.add_argument("--data-split", help="the former spelling of --split with --onnx")
    s.add_argument("--runtime", choices=RUNTIMES, default="onnxruntime", help="with --onnx: inference runtime")
    s.add_argument("--bootstrap", type=_positive_int, default=200, help="bootstrap resamples for 95%% intervals")
    s.add_argument("--seed", type=_nonnegative_int, default=0, help="seed of the bootstrap resampling (default 0)")
    s.set_defaults(func=cmd_evaluate)


def _add_run(sub, quiet) -> None:
    s = sub.add_parser("run", parents=[quiet], **command_text("run"),
                       help="the whole benchmark: simulate, train, export, predict, evaluate, report")
    s.add_argument("--profile", choices=["quick", "default", "full"], default="default",
                   help="quick: a smoke run in minutes; default: compact models on 2 CPU cores (about 3 h a draw); "
                        "full: the references' settings (GPU)")
    s.add_argument("--models", help="comma-separated model names, as listed above (default: all available); "
                                     "none: only the imported models of --checkpoints (no training set is made)")
    s.add_argument("--checkpoints", metavar="DIR", type=_path,
                   help="checkpoints written by `sotif-bench import` (a folder of .pt files, or one file): each is "
                        "evaluated beside the --models as <model>_<source> (e.g. second_openpcdet), with its "
                        "published weights and no training; with --models none --lidar-model carla --instances 1 "
                        "this is the source study's protocol (docs/published.md)")
    s.add_argument("--out", type=_folder, help="run directory (default reports/<profile>)")
    s.add_argument("--runtime", choices=RUNTIMES, default="onnxruntime", help="inference runtime (default onnxruntime)")
    s.add_argument("--jobs", type=_positive_int,
                   help="models trained/exported/predicted at once (default: the profile's, 2; 1 = one after the other)")
    s.add_argument("--lidar-model", choices=["physics", "carla"], default=None,
                   help="physics: the weather changes the point cloud (default); carla: CARLA's weather-blind LiDAR, "
                        "the paper's protocol (the data sets, and so every stage after them, are made again)")
    s.add_argument("--seeds", type=_positive_int,
                   help="training draws per model, seeds 0..K-1 (default 1); the tables show their mean and range")
    s.add_argument("--warm-start", action=argparse.BooleanOptionalAction, default=None,
                   help="start PV-RCNN and Part-A2 from the run's SECOND, MVX-Net from its DV-SECOND "
                        "(those train first, and are trained too when --models leaves them out; a changed "
                        "sibling retrains them); on in the quick and default profiles, off in full")
    s.add_argument("--instances", type=_positive_int,
                   help="scenario instances per weather preset in the SOTIF set (default: the profile's, 2 in "
                        "default; 1 = the study's one scripted drive per preset); more give a finer SOTIF map and "
                        "narrower intervals for prediction time, not training time")
    s.add_argument("--sweep-instances", type=_positive_int,
                   help="instances of the weather sweep set over rain rate, fog visibility and road water "
                        "(default: the profile's, 30 in default)")
    s.set_defaults(func=cmd_run)


def _add_verdict(sub, quiet) -> None:
    s = sub.add_parser("verdict", parents=[quiet], help="the SOTIF verdict of a detector's predictions on a scenario set",
                       **command_text("verdict"))
    s.add_argument("--data", required=True, help="a scenario set (simulate --instances N, or --preset sweep)")
    s.add_argument("--predictions", required=True, help="folder of KITTI result files of the set's frames (predict)")
    s.add_argument("--output", required=True, type=_path, help="FILE.csv: the instance table; other names: JSON")
    s.add_argument("--latency-ms", type=float,
                   help="the detector's latency per frame (e.g. its p90): adds the system verdict, on the frames it "
                        "can process, the latency added to the decision time (default: perception verdict only)")
    s.add_argument("--threshold", type=float,
                   help="the detector's operating score threshold (default: F1-optimal on the set's val split "
                        "when it is predicted, else 0.3)")
    s.add_argument("--split", default="test", help="the split judged (default test)")
    s.add_argument("--reaction", choices=["system", "human"], default="system",
                   help="reaction time after the confirmation: an automated system's 0.35 s (UN R157) or a "
                        "driver's 1.0 s (default system)")
    s.add_argument("--model", help="the name in the rows (default: the predictions folder's name)")
    s.add_argument("--force", action="store_true", help="write --output even inside an input folder")
    s.set_defaults(func=cmd_verdict)


def _add_report(sub, quiet) -> None:
    s = sub.add_parser("report", parents=[quiet], help="re-render a run directory's HTML and Markdown report",
                       **command_text("report"))
    s.add_argument("run_dir", nargs="?", help="the run folder (reports/NAME); optional with --docs")
    s.add_argument("--sample", metavar="DIR", type=_folder,
                   help="then copy the report, tables/*.csv and figures into DIR (the repository's reports/sample), "
                        "replacing a previous sample there; a DIR holding anything else is refused")
    s.add_argument("--docs", action="store_true",
                   help="then rewrite the blocks of this checkout's README.md and docs/results.md marked "
                        "<!-- sample:NAME --> from the sample's tables (--sample DIR, default reports/sample); "
                        "without a run folder, only that; exit 2 naming the table when a block cannot be made")
    s.set_defaults(func=cmd_report)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sotif-bench", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"sotif-bench {_version()}")
    p.add_argument("--quiet", action="store_true", help="no progress bars or progress lines")
    # --quiet also after the subcommand (``sotif-bench evaluate --quiet ...``)
    quiet = argparse.ArgumentParser(add_help=False)
    quiet.add_argument("--quiet", action="store_true", default=argparse.SUPPRESS,
                       help="no progress bars or progress lines")
    sub = p.add_subparsers(dest="command", required=True, parser_class=CommandParser)
    _add_simulate(sub, quiet)
    _add_train(sub, quiet)
    _add_export(sub, quiet)
    _add_import(sub, quiet)
    _add_predict(sub, quiet)
    _add_evaluate(sub, quiet)
    _add_run(sub, quiet)
    _add_verdict(sub, quiet)
    _add_report(sub, quiet)
    return p


def _bad_input(e: Exception) -> bool:
    """Errors that are the input's, not the program's: ValueErrors (``harness.core.kitti.KittiError`` and
    ``harness.infer.ContractError`` among them), bad paths, and full or read-only disks."""
    return (isinstance(e, (ValueError, FileNotFoundError, NotADirectoryError, IsADirectoryError, FileExistsError,
                           PermissionError))
            or isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.ENAMETOOLONG,
                                                       errno.ELOOP)
            or isinstance(e, RuntimeError) and str(e).startswith("Symlink loop"))  # pathlib's resolve(strict=False)


def _close_bars() -> None:
    """Close the progress bars a failed step left open: each bar's line ends there."""
    from tqdm import tqdm
    for bar in list(getattr(tqdm, "_instances", ())):
        bar.close()


def _message(text: str) -> None:
    """An error or notice on stderr on its own line, never onto a progress bar."""
    _close_bars()
    print(text, file=sys.stderr, flush=True)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from harness.compile_notice import announce_compiles
    from harness.malloc import keep_freed_memory
    keep_freed_memory()
    announce_compiles()
    try:
        return args.func(args)
    except KeyboardInterrupt:
        _message(f"sotif-bench {args.command}: interrupted; run the same command again to resume")
        return 130
    except Exception as e:  # noqa: BLE001 - bad input exits 2, anything else is reported and exits 1
        if _bad_input(e):
            _message(f"sotif-bench {args.command}: error: {e}")  # the file and the problem
            return BAD_INPUT
        _close_bars()
        traceback.print_exc()
        _message(f"sotif-bench {args.command}: internal error (see the trace above)")
        return INTERNAL


if __name__ == "__main__":
    sys.exit(main())
