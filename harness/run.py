"""``sotif-bench run``: simulate -> train -> export -> predict -> evaluate -> report.

Every stage writes its files and a record ``RUN/.stages/<stage>.json`` holding the hash of its
inputs and config and of each file it wrote (``harness.stages``); a stage whose record matches and
whose files are as it wrote them is skipped, so a second run only redoes what changed or was
damaged, and an interrupted run resumes (each stage also resumes inside itself: the simulator
per frame, training per epoch, prediction per frame).

Training draws: with ``seeds`` K > 1 every model is trained K times, with the training seeds
``seed`` .. ``seed + K - 1``. Draw 0 keeps the single draw's files (``models/<name>/``,
``models/<name>.onnx``, ``predictions/<name>/``, ``results/<name>.json``), so a run with
``--seeds 2`` resumes a finished run of one draw; draw d > 0 writes the same files under the
name ``<name>.seed<d>``. ``results.json`` then lists every draw under ``draws``. A later draw is
predicted on the SOTIF test and val sets (its headline AP and val AP in tables/draws.csv and the paired
table), not on the sweep set: the scenario-space verdict and the boundaries judge draw 0.
"""
from __future__ import annotations

import contextlib
import heapq
import json
import os
import signal
import sys
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass, replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from harness import data_identity, provenance, published_run, valset
from harness.core.files import atomic_write_text, folder_lock, remove_temp_files
from harness.jobs import interrupted, job_init
from harness.model_stages import checkpoint_of, export_stage, import_export
from harness.predict_eval import predict_evaluate
from harness.run_boundaries import boundaries_stage
from harness.stages import Stages, file_digest
from models.recipe import ModelRecipe

RUN_SCHEMA = "sotif-bench/run/1"
GROUP_COLUMNS = ("weather", "time_of_day", "precipitation_class")


@dataclass(frozen=True)
class RunConfig:
    """What a run does; a profile is a named RunConfig."""

    profile: str
    model_profile: str  # the detectors' config profile: tiny | compact | kitti
    train_frames: int
    sotif_frames: int | None  # None: the full 547-frame SOTIF set
    epochs: int | None  # None: each model's own default for its profile
    seed: int = 0
    workers: int = 2
    device: str = "cpu"
    runtime_frames: int = 20  # frames timed in torch eager and compared with onnxruntime
    jobs: int = 2  # models trained/exported/predicted at once, each process with cores // jobs threads
    bootstrap: int = 200
    lidar_model: str = "physics"
    seeds: int = 1  # training draws per model: seeds seed .. seed + seeds - 1
    warm_start: bool = True  # two-stage and fusion models start from their one-stage sibling (Recipe.warm_from)
    sotif_instances: int | None = None  # scenario instances per weather of the SOTIF set; None: the study's one
    sweep_instances: int | None = None  # instances of the weather sweep set (data/sweep); None: no sweep set
    val_frames: int | None = None  # the val set's held-out training-generator frames (harness.valset); None: none
    published: tuple = ()  # (tag, checkpoint file) of the imported models the run evaluates (harness.published_run)
    bounds: str | None = None  # the boundary searches' plan (harness.run_boundaries.PLANS); None: none


def model_recipes(cfg: RunConfig, names: list[str]) -> dict[str, ModelRecipe]:
    """Each model the run trains, resolved once: its network, config and schedule in the run's model
    profile, and with ``warm_start`` the sibling whose checkpoint starts it (the same draw's: the sibling
    trains first, and a changed sibling retrains it)."""
    from models.zoo import resolve
    return {name: resolve(name, cfg.model_profile, warm=cfg.warm_start) for name in names}


def _sibling(recipe: ModelRecipe | None, tag: str) -> str | None:
    """The tag whose checkpoint starts ``tag``'s training (None: a cold start or an imported model)."""
    if recipe is None or recipe.warm_from is None:
        return None
    return recipe.warm_from + tag[len(recipe.model):]  # the same draw's suffix


def with_siblings(cfg: RunConfig, run_dir: Path, names: list[str], progress: bool = True) -> list[str]:
    """``names`` and, with ``warm_start``, the siblings their trainings start from that neither ``names``
    nor ``run_dir`` (in every draw) holds (``run --models pv_rcnn`` also trains SECOND, as the default run
    does)."""
    from models.zoo import recipe
    extra = []
    for name in names:
        sib = recipe(name).warm_from if cfg.warm_start else None
        held = sib and all(checkpoint_of(run_dir, draw_tag(sib, d)).is_file() for d in range(cfg.seeds))
        if sib and sib not in names + extra and not held:
            extra.append(sib)
            if progress:
                print(f"{name} starts from {sib}'s first stage: {sib} is trained too (--no-warm-start: "
                      f"{name} from nothing)", flush=True)
    return names + extra


def draw_tag(name: str, draw: int) -> str:
    """The file and stage name of a model's training draw (the model's own name for draw 0)."""
    return name if draw == 0 else f"{name}.seed{draw}"


def _model_of(tag: str) -> str:
    return tag.split(".seed")[0]


PROFILES = {
    # default: 30 sweep instances, 10 per weather axis, so that a condition bin can hold >= 5 instances
    # quick: the study's SOTIF set cut to 42 frames and a 3-instance sweep set (smoke run, numbers mean nothing)
    "quick": RunConfig("quick", "tiny", train_frames=40, sotif_frames=42, epochs=2, bootstrap=50, runtime_frames=3,
                       sweep_instances=3, val_frames=10, bounds="quick"),
    # default's 1,800 training scenes (1,530 train, 270 val) at the steps that 300 took before: the same val AP
    # mean, a higher and narrower headline over draws (docs/performance.md, "Training levers over draws")
    "default": RunConfig("default", "compact", train_frames=1800, sotif_frames=None, epochs=None, runtime_frames=20,
                         sotif_instances=2, sweep_instances=30, val_frames=300, bounds="default"),
    # the references train every model from nothing: so does the full profile
    "full": RunConfig("full", "kitti", train_frames=3000, sotif_frames=None, epochs=None, device="cuda", jobs=1,
                      warm_start=False),
}

# Minutes of each model's job (train, export, predict the SOTIF, sweep and val sets, evaluate) on one core of
# the sample's Intel Xeon, idle (docs/performance.md, "The default run's stages"): the job pool starts the
# longest first, so that the jobs end together, and the ETA a run prints scales them by the share of each job
# still to do. Part-A2's and PointRCNN's training minutes scaled by their schedules' steps over the 1,800 scenes
# (0.75 and 1.2 of those measured).
_SAMPLE_MINUTES = {"mvx_net": 48, "point_rcnn": 88, "pointpillars": 29, "pv_rcnn": 47, "second": 34, "dv_second": 41,
                   "parta2": 38}


# What a simulate stage records of its data set: every file the simulator writes (scans, images,
# calibrations, labels, road planes, splits, the per-frame records and meta/dataset.json); not the
# toolkit views (symlinks to these files) nor the ground-truth database training adds. The scans are
# re-read only when their mtime changed (``by_stat``): checking the default run's 847 frames (1.3 GB)
# takes 0.2-0.6 s, against 1.7-8 s for hashing every byte (docs/performance.md).
DATA_PARTS = ("training/velodyne", "training/image_2", "training/calib", "training/label_2", "training/planes",
              "ImageSets", "meta")


SIM_SEED_OFFSET = {"sotif": 0, "train": 1000, "sweep": 2000}  # each data set's simulation seed: run seed + offset


def simulate_set(stages: Stages, cfg: RunConfig, data_dir: Path, preset: str,
                 weathers: list[str] | None = None) -> str:
    """Simulate (or resume) a data set; returns the hash of its ``meta/dataset.json``, which lists the
    SHA-256 of every frame's files: the stages that read the data set key on it. A changed, truncated or
    missing file of the set is removed and the simulator makes its frame again (the same bytes: it seeds
    every frame), so the stages after it redo nothing unless the data set's bytes differ. The SOTIF and
    sweep sets are drawn with ``cfg.sotif_instances`` / ``cfg.sweep_instances`` scenario instances (a
    SOTIF set of None instances is the study's one instance per weather, keyed as it always was); ``weathers``
    replaces the preset's own (keyed only when given)."""
    from simulator import generate
    instances = {"train": None, "sotif": cfg.sotif_instances, "sweep": cfg.sweep_instances}[preset]
    if preset == "sotif" and instances == 1:
        instances = None  # one instance per weather is the study's set, capped and keyed as run --instances 1 makes it
    # an instance set's size is its instance count: frames are not capped
    frames = None if instances is not None else {"train": cfg.train_frames, "sotif": cfg.sotif_frames}[preset]
    seed = cfg.seed + SIM_SEED_OFFSET[preset]
    out = data_dir / preset
    from simulator.dataset import GENERATOR_VERSION
    # the run's own val set picks the operating thresholds: an instance set is then all test
    val_share = {"val_share": 0.0} if instances is not None and cfg.val_frames else {}
    chosen = {"weathers": list(weathers)} if weathers is not None else {}
    key = {"preset": preset, "frames": frames, "seed": seed, "lidar": cfg.lidar_model, "generator": GENERATOR_VERSION,
           **({"instances": instances} if instances is not None else {}), **val_share, **chosen}
    more = {**({"instances": instances, **val_share} if instances is not None else {}), **chosen}
    # force: the folder is the run's own, and a changed key (e.g. another --lidar-model) simulates it
    # again over the data set of the old one; a partial one of the same key still resumes
    stages.run(f"simulate_{preset}", key, lambda: {"out": str(generate(
        out, preset=preset, frames=frames, seed=seed, workers=cfg.workers, lidar_model=cfg.lidar_model,
        progress=stages.progress, force=True, **more))}, outputs=[out / part for part in DATA_PARTS], by_stat=True)
    return file_digest(out / "meta" / "dataset.json")


def _train_export(stages: Stages, cfg: RunConfig, run_dir: Path, recipe: ModelRecipe, tag: str, train_hash: str,
                  draw: int = 0) -> dict:
    from harness.train import train
    ckpt = checkpoint_of(run_dir, tag)
    seed = cfg.seed + draw
    sibling = _sibling(recipe, tag)
    init = checkpoint_of(run_dir, sibling) if sibling else None
    warm = {"init_from": {"model": sibling, "checkpoint": file_digest(init)}} if init else {}
    tinfo = stages.run(f"train_{tag}", {"model": recipe.model, "profile": recipe.profile, "epochs": cfg.epochs,
                                         "schedule": recipe.schedule.key(), "model_config": asdict(recipe.config),
                                         "data": train_hash, "seed": seed, **warm},
                       lambda: {"checkpoint": str(train(recipe, run_dir / "data" / "train", ckpt.parent,
                                                        epochs=cfg.epochs, device=cfg.device, seed=seed,
                                                        init_from=init, progress=stages.bars,
                                                        on_epoch=stages.epoch_line(tag)))},
                       outputs=[ckpt])
    export_stage(stages, run_dir, tag, recipe.model)
    return tinfo


def _checkpoint_meta(ckpt: Path) -> dict:
    from models.zoo import read_checkpoint
    state = read_checkpoint(ckpt)
    params = sum(int(np.prod(v.shape)) for v in state["state_dict"].values() if hasattr(v, "shape")
                 and v.dtype.is_floating_point)
    return {"params": params, "epochs": state.get("epoch"), "final_loss": state.get("final_loss"),
            "val_ap": state.get("val_ap"), "val_history": state.get("val_history"),
            "train_seconds": state.get("train_seconds")}


def _predict_eval(stages: Stages, cfg: RunConfig, run_dir: Path, name: str, sotif_hash: str, runtime: str,
                  threads: int | None = None, sweep_hash: str | None = None) -> dict:
    from harness.infer import predict
    data, pred = run_dir / "data" / "sotif", run_dir / "predictions" / name
    key = predict_evaluate(stages, cfg, run_dir, name, "", data, sotif_hash, "test", pred,
                           run_dir / "results" / f"{name}.json", runtime, threads, group_by=GROUP_COLUMNS)
    if (data / "ImageSets" / "val.txt").stat().st_size:
        stages.run(f"predict_val_{name}", key, lambda: {"summary": predict(run_dir / "models" / f"{name}.onnx", data,
                                                                           run_dir / "predictions_val" / name,
                                                                           split="val", runtime=runtime, progress=False,
                                                                           threads=threads)},
                   outputs=[run_dir / "predictions_val" / name])
    if sweep_hash is not None:
        from harness.run_space import predict_eval_sweep
        predict_eval_sweep(stages, cfg, run_dir, name, sweep_hash, runtime, threads)
    return json.loads((pred / "predict.json").read_text())


def _runtime_probe(stages: Stages, cfg: RunConfig, run_dir: Path, name: str) -> dict:
    import importlib.util
    from harness.runtime import BOX_ATOL, compare_openvino, compare_torch_onnx
    onnx_path = run_dir / "models" / f"{name}.onnx"
    data = run_dir / "data" / "sotif"
    has_ov = importlib.util.find_spec("openvino") is not None
    # the tolerance of "same boxes" is part of what the probe measured
    key = {"onnx": file_digest(onnx_path), "frames": cfg.runtime_frames, "openvino": has_ov, "box_atol": BOX_ATOL}
    return stages.run(f"runtime_{name}", key,
                      lambda: {**compare_torch_onnx(checkpoint_of(run_dir, name), onnx_path, data,
                                                    n_frames=cfg.runtime_frames),
                               "openvino": compare_openvino(onnx_path, data, n_frames=cfg.runtime_frames)})


def _model_summary(cfg, run_dir: Path, name: str, tinfo: dict, ort: dict, probe: dict) -> dict:
    from harness.infer import check_contract
    from harness.run_space import space_summary
    from harness.sotif import sotif_view
    onnx_path = run_dir / "models" / f"{name}.onnx"
    info = check_contract(onnx_path)
    ck = _checkpoint_meta(checkpoint_of(run_dir, name))
    data = run_dir / "data" / "sotif"
    view = sotif_view(data, run_dir / "predictions" / name, split="test",
                      val_predictions_dir=run_dir / "predictions_val" / name, **valset.threshold_of(run_dir, name))
    runtime = {"prediction": ort, **{k: v for k, v in probe.items() if k != "seconds"},
               "onnxruntime": probe.get("onnxruntime") or ort}
    threshold = next(iter(view.values()))["threshold"]
    return {"architecture": info.architecture, "two_stage": info.two_stage, "uses_camera": info.uses_camera,
            "onnx": f"models/{name}.onnx", "size_mb": onnx_path.stat().st_size / 2**20, "params": ck["params"],
            "op_histogram": info.op_histogram, "provenance": info.provenance,
            # the checkpoint's own training time (summed over resumed sessions), else the stage's
            "train": {"seconds": ck["train_seconds"] or tinfo.get("seconds"), "epochs": ck["epochs"], "final_loss": ck["final_loss"],
                      "val_ap": ck["val_ap"], "val_history": ck["val_history"]},
            # latency measured by the probe with the machine to itself; the prediction stage's own
            # figures (all test frames, possibly beside another job) stay under "prediction"
            "runtime": runtime, "results": f"results/{name}.json", "sotif": view, "val": valset.val_summary(run_dir, name),
            **space_summary(run_dir, name, threshold, runtime)}


def _model_job(cfg: RunConfig, run_dir: Path, tag: str, recipe: ModelRecipe | None, train_hash: str, sotif_hash: str,
               runtime: str, progress: bool, threads: int | None, bars: bool, draw: int = 0,
               sweep_hash: str | None = None) -> tuple[dict, dict]:
    """Train, export, predict and evaluate one model's draw (in the run's process or a job process);
    ``recipe``: the model's (None: an imported model's)."""
    if interrupted():  # a job process that was interrupted takes no further job from the pool's queue
        raise KeyboardInterrupt("the run was interrupted")
    stages = Stages(run_dir, progress, bars=bars, prefix=f"[{tag}] " if not bars else "")
    if published_run.source(cfg, tag):
        tinfo = import_export(stages, cfg, run_dir, tag)
    else:
        tinfo = _train_export(stages, cfg, run_dir, recipe, tag, train_hash, draw)
    # the scenario-space verdict and the boundaries judge draw 0; later draws add the SOTIF headline and val
    ort = _predict_eval(stages, cfg, run_dir, tag, sotif_hash, runtime, threads, sweep_hash if draw == 0 else None)
    valset.predict_evaluate(stages, cfg, run_dir, tag, runtime, threads)
    return tinfo, ort


def _model_jobs(cfg: RunConfig, run_dir: Path, models: list[str], recipes: dict[str, ModelRecipe], train_hash: str,
                sotif_hash: str, runtime: str, progress: bool, t0: float,
                sweep_hash: str | None = None) -> dict[str, tuple[dict, dict]]:
    """``_model_job`` for every model and training draw (keyed by :func:`draw_tag`; ``recipes``: those of
    the trained models, :func:`model_recipes`): ``cfg.jobs``
    processes at once with ``cores // jobs`` threads each (the sparse and point-based networks gain
    little from a second thread in one step, so two models side by side finish sooner than one
    after the other), or in this process."""
    say = (lambda msg: print(msg, flush=True)) if progress else (lambda msg: None)
    draws = {draw_tag(n, d): d for d in range(cfg.seeds) for n in models if d < published_run.draws(cfg, n)}
    names = list(draws)
    waits = {}  # the sibling a job waits for: one trained in this run (an earlier run's checkpoint waits for nothing)
    recipe_of = {n: recipes.get(_model_of(n)) for n in names}  # None: an imported model
    for n in names:
        sib = _sibling(recipe_of[n], n)
        if sib in draws:
            waits[n] = sib
        elif sib and not checkpoint_of(run_dir, sib).is_file():
            raise ValueError(f"--warm-start: {n} starts from {sib}, which is neither among the models of this run "
                             f"nor trained in {run_dir} (add {_model_of(sib)} to --models)")
    jobs = max(1, min(cfg.jobs, len(names)))
    order = sorted(names, key=lambda n: -_SAMPLE_MINUTES.get(_model_of(n), 10)) if jobs > 1 else \
        sorted(names, key=lambda n: n in waits)  # one slot: siblings first
    minutes = {n: _SAMPLE_MINUTES.get(_model_of(n), 10) * _work_left(cfg, run_dir, n, recipe_of[n]) for n in names}
    done: dict[str, tuple[dict, dict]] = {}
    starts: dict[str, float] = {}  # a job starts when a slot frees and its sibling is done
    ends: dict[str, float] = {}

    def next_ready() -> str | None:
        return next((n for n in order if n not in starts and (n not in waits or waits[n] in done)), None)

    def finished(name: str, result) -> None:
        done[name] = result
        now = time.perf_counter()
        ends[name] = now
        left = _eta_seconds(order, minutes, starts, ends, now, jobs) if len(done) < len(names) else None
        eta = f", ETA {left:.0f} s" if left is not None else ""
        say(f"== {name} done ({len(done)}/{len(names)} models, elapsed {now - t0:.0f} s{eta})")

    if progress and (first := _start_eta(cfg, order, minutes, jobs)):
        say(first)
    if jobs == 1:
        for i, name in enumerate(order, 1):
            starts[name] = time.perf_counter()
            say(f"== model {i}/{len(names)}: {name} (elapsed {time.perf_counter() - t0:.0f} s)")
            finished(name, _model_job(cfg, run_dir, name, recipe_of[name], train_hash, sotif_hash, runtime, progress,
                                      None, progress, draws[name], sweep_hash))
        return done
    import multiprocessing
    threads = max(1, (os.cpu_count() or 1) // jobs)
    say(f"== {len(names)} models, {jobs} at a time with {threads} thread(s) each: {', '.join(order)}")
    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn"), initializer=job_init,
                             initargs=(threads, os.getpid())) as pool:
        pending = {}

        def submit_ready() -> None:  # fill the free slots with jobs whose siblings are done
            while len(pending) < jobs and (name := next_ready()) is not None:
                starts[name] = time.perf_counter()
                pending[pool.submit(_model_job, cfg, run_dir, name, recipe_of[name], train_hash, sotif_hash, runtime,
                                    progress, threads, False, draws[name], sweep_hash)] = name

        submit_ready()
        try:
            while pending:
                ready, _ = wait(pending, return_when=FIRST_COMPLETED)
                for fut in ready:
                    name = pending.pop(fut)
                    finished(name, fut.result())
                submit_ready()
        except BaseException:
            # the jobs stop too (a SIGINT sent to this process alone would otherwise let them train
            # on, and the pool's queue would start more): what they wrote stays, atomic files
            for proc in list((getattr(pool, "_processes", None) or {}).values()):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(proc.pid, signal.SIGINT)
            pool.shutdown(wait=True, cancel_futures=True)
            raise
    return done


def _eta_seconds(order: list[str], minutes: dict[str, float], starts: dict[str, float], ends: dict[str, float],
                 now: float, jobs: int) -> float:
    """Seconds until the last of ``order``'s model jobs ends: each job is expected to take its
    ``minutes`` (the work it has left, in sample-run minutes) scaled by how long the finished ones
    took against theirs (jobs expected to take under a minute, resumed near their end, do not
    count), the running ones less what they have run, and the queued ones go to whichever of the
    ``jobs`` slots frees first."""
    timed = [n for n in ends if minutes[n] >= 1]
    per_minute = (sum(ends[n] - starts[n] for n in timed) / sum(minutes[n] for n in timed)) if timed else 60.0
    running = [n for n in order if n in starts and n not in ends]
    free = [max(0.0, per_minute * minutes[n] - (now - starts[n])) for n in running]
    free += [0.0] * max(0, jobs - len(free))
    heapq.heapify(free)
    for n in order:
        if n not in starts:
            heapq.heappush(free, heapq.heappop(free) + per_minute * minutes[n])
    return max(free)


def _start_eta(cfg: RunConfig, order: list[str], minutes: dict[str, float], jobs: int) -> str:
    """The model jobs' ETA before any has ended, from the sample run's minutes (``_SAMPLE_MINUTES``, measured in
    the default profile) scaled by the work each job has left; "" for other profiles (other networks and
    schedules: their first ETA comes with the first job's end)."""
    if cfg.profile != "default" or not order:
        return ""
    left = _eta_seconds(order, minutes, {}, {}, 0.0, jobs)
    return (f"== model jobs: about {left / 60:.0f} min at the sample machine's job times (docs/performance.md); "
            "the ETA printed as each job ends scales them by this machine's")


def _work_left(cfg: RunConfig, run_dir: Path, name: str, recipe: ModelRecipe | None) -> float:
    """The share of a model's job still to do (0..1), from the epochs its checkpoint holds and the test
    frames already predicted: training is most of a job (about 60 % in the sample run), prediction
    most of the rest."""
    from models.zoo import CheckpointError, read_checkpoint
    test = run_dir / "data" / "sotif" / "ImageSets" / "test.txt"
    n_test = len(test.read_text().split()) if test.is_file() else 0
    predicted = len(list((run_dir / "predictions" / name).glob("[0-9]*.txt")))
    if recipe is None:  # an imported model: nothing to train
        return 0.4 * max(0.0, 1 - predicted / n_test) if n_test else 0.4
    epochs = cfg.epochs or recipe.schedule.epochs
    ckpt = checkpoint_of(run_dir, name)
    try:
        done = read_checkpoint(ckpt).get("epoch", 0) if ckpt.is_file() else 0
    except CheckpointError:
        done = 0  # the train stage says what is wrong with it
    return 0.6 * max(0.0, 1 - done / epochs) + 0.4 * max(0.0, 1 - predicted / n_test) if n_test else 1.0


def _gt_database(cfg: RunConfig, run_dir: Path, recipes: dict[str, ModelRecipe]) -> None:
    """Build the training set's ground-truth database once, before jobs that would race to build it."""
    from harness.augment import AugmentConfig
    from harness.gt_database import load_or_build
    from harness.train import uses_gt_sampling
    aug = AugmentConfig()  # what train() uses
    if cfg.jobs > 1 and any(uses_gt_sampling(r.build(), aug) for r in recipes.values()):
        data = run_dir / "data" / "train"
        load_or_build(data, data / "gt_database", aug.gt_sampling)


def resolve(profile: str, models, out, config: RunConfig | None = None) -> tuple[RunConfig, list[str], Path]:
    if config is None and profile not in PROFILES:
        raise ValueError(f"unknown profile {profile!r}; expected one of {', '.join(PROFILES)}")
    from models.zoo import MODEL_NAMES, available
    cfg = config or PROFILES[profile]
    if cfg.device == "cuda":
        import torch
        if not torch.cuda.is_available():
            cfg = replace(cfg, device="cpu")
            print(f"sotif-bench run: no CUDA device here: the {cfg.profile} profile's {cfg.model_profile} models "
                  f"train on the CPU ({cfg.train_frames} training scenes, each model on its {cfg.model_profile} "
                  "schedule, OpenPCDet's GPU settings)", file=sys.stderr, flush=True)
    names = list(models) if models is not None else list(available())
    bad = [m for m in names if m not in MODEL_NAMES]
    if bad:
        raise ValueError(f"unknown model(s) {', '.join(bad)}; expected names from {', '.join(MODEL_NAMES)}")
    missing = [m for m in names if m not in available()]
    if missing:
        raise ValueError(f"model(s) {', '.join(missing)} are not available in this installation")
    return cfg, names, Path(out) if out else Path("reports") / profile


def _refuse_foreign_folder(run_dir: Path) -> None:
    """A run writes config.json, report.md, index.html and more into its folder: one that holds
    files but no run (no stage record, no run config) is refused, not written over."""
    visible = sorted(p.name for p in run_dir.iterdir() if not p.name.startswith(".")) if run_dir.is_dir() else []
    if not visible or (run_dir / ".stages").is_dir():  # hidden ones: a lock or temp file of a run
        return
    try:
        config = json.loads((run_dir / "config.json").read_text())
        if isinstance(config, dict) and {"profile", "models"} <= set(config):
            return  # a run stopped before its first stage ended
    except (OSError, ValueError):
        pass
    raise ValueError(f"{run_dir}: holds files ({visible[0]}, ...) but no sotif-bench run; choose another --out "
                     "(an empty or new folder, or a run's folder to resume it)")


def run(profile: str = "default", models=None, out=None, progress: bool = True, runtime: str = "onnxruntime",
        config: RunConfig | None = None, jobs: int | None = None, seeds: int | None = None,
        lidar_model: str | None = None, warm_start: bool | None = None, instances: int | None = None,
        sweep_instances: int | None = None, checkpoints=None) -> Path:
    """The whole benchmark into ``out`` (default reports/<profile>); returns the run directory.

    ``config`` replaces the profile's RunConfig (tests use a smaller one); ``jobs`` its number of
    models run at once (not part of any stage key: changing it redoes nothing); ``seeds`` its
    number of training draws per model; ``lidar_model`` "carla" simulates every data set with
    CARLA's weather-blind LiDAR (the paper's protocol); ``warm_start`` starts PV-RCNN and Part-A2
    from the run's SECOND and MVX-Net from its DV-SECOND (their ``Recipe.warm_from``), which then train first;
    ``instances`` the SOTIF set's scenario instances per weather (1: the study's set) and
    ``sweep_instances`` the sweep set's (a finer map costs prediction time, not training); ``checkpoints``
    a checkpoint ``import`` wrote, or a folder of them, evaluated beside ``models`` (``harness.published_run``;
    ``models`` [] runs them alone, and no training set is simulated)."""
    from harness.report import render
    cfg, names, run_dir = resolve(profile, models, out, config)
    for flag, value in (("instances", instances), ("sweep instances", sweep_instances)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ValueError(f"{flag} must be an integer >= 1, got {value!r}")
    if instances is not None:  # 1: the study's one scripted instance per weather
        cfg = replace(cfg, sotif_instances=None if instances == 1 else instances,
                      sotif_frames=cfg.sotif_frames if instances == 1 else None)
    if sweep_instances is not None:
        cfg = replace(cfg, sweep_instances=sweep_instances)
    if jobs is not None:
        cfg = replace(cfg, jobs=jobs)
    if lidar_model is not None:
        cfg = replace(cfg, lidar_model=lidar_model)
    if warm_start is not None:
        cfg = replace(cfg, warm_start=warm_start)
    if seeds is not None:
        if seeds < 1:
            raise ValueError(f"seeds must be >= 1, got {seeds}")
        cfg = replace(cfg, seeds=seeds)
    profile = cfg.profile
    names = with_siblings(cfg, run_dir, names, progress)
    cfg, names = published_run.add(cfg, names, checkpoints)
    trained = published_run.trained(cfg, names)
    recipes = model_recipes(cfg, trained)
    _refuse_foreign_folder(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    with folder_lock(run_dir, "run"):
        stale = remove_temp_files(run_dir)
        if stale and progress:
            print(f"removed {len(stale)} temp file(s) of writes an interrupted run left unfinished", flush=True)
        code = provenance.record()  # the commit and sources digest that the report compares with the checkout
        atomic_write_text(run_dir / "config.json", json.dumps({**asdict(cfg), "models": names, "runtime": runtime,
                                                               "code": code}, indent=1))
        stages = Stages(run_dir, progress)
        t0 = time.perf_counter()
        train_hash = simulate_set(stages, cfg, run_dir / "data", "train") if trained else None
        sotif_hash = simulate_set(stages, cfg, run_dir / "data", "sotif")
        sweep_hash = simulate_set(stages, cfg, run_dir / "data", "sweep") if cfg.sweep_instances else None
        valset.simulate(stages, cfg, run_dir, DATA_PARTS)
        data_identity.write_data_sets(run_dir)
        for line in data_identity.compare(run_dir) if progress else ():
            print(line, flush=True)
        _gt_database(cfg, run_dir, recipes)
        done = _model_jobs(cfg, run_dir, names, recipes, train_hash, sotif_hash, runtime, progress, t0, sweep_hash)
        summary = {}
        for name in names:  # one model at a time: the latency figures own the machine
            probe = _runtime_probe(stages, cfg, run_dir, name)
            entry = _model_summary(cfg, run_dir, name, *done[name], probe)
            summary[name] = published_run.mark(cfg, run_dir, name, entry)
        boundaries_stage(stages, cfg, run_dir, summary, runtime)
        data_stats(run_dir)
        ids = lambda s, d="sotif": len((run_dir / "data" / d / "ImageSets" / f"{s}.txt").read_text().split())
        infos = {p.stem: json.loads(p.read_text())["info"] for p in sorted((run_dir / ".stages").glob("*.json"))}
        result = {"schema": RUN_SCHEMA, "profile": profile, "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                  "config": asdict(cfg), "code": code, "models": summary,
                  "data": {"n_test_frames": ids("test"), "n_val_frames": ids("val"),
                           "n_train_frames": ids("train", "train") if trained else None,
                           "stats": "tables/data_stats.csv"},
                  "stage_seconds": {n: i.get("seconds") for n, i in infos.items()},
                  "wall_seconds": _wall_span(infos)}
        if cfg.seeds > 1:
            result["draws"] = {n: [_draw_summary(run_dir, draw_tag(n, d), cfg.seed + d) for d in range(cfg.seeds)]
                               for n in trained}
        atomic_write_text(run_dir / "results.json", json.dumps(result, indent=1, default=str))
        render(run_dir)
    return run_dir


def _draw_summary(run_dir: Path, tag: str, seed: int) -> dict:
    """One training draw of a model: its seed, files, val AP and the headline AP of its predictions."""
    ck = _checkpoint_meta(checkpoint_of(run_dir, tag))
    res = json.loads((run_dir / "results" / f"{tag}.json").read_text())
    return {"tag": tag, "seed": seed, "onnx": f"models/{tag}.onnx", "results": f"results/{tag}.json",
            "val_ap": ck["val_ap"], "val_history": ck["val_history"], "val": valset.val_summary(run_dir, tag),
            "headline": res["headline"],
            "distance": res["distance"]}


def _wall_span(infos: dict[str, dict]) -> float | None:
    """Seconds during which at least one stage ran: the length of the union of the stages' intervals.
    Stages of parallel jobs overlap, so this is less than their sum; a run stopped and resumed
    later does not count the pause. None when a record predates the ``finished`` stamp."""
    spans = sorted((i["finished"] - i["seconds"], i["finished"]) for i in infos.values()
                   if isinstance(i.get("finished"), (int, float)) and isinstance(i.get("seconds"), (int, float)))
    if not spans or len(spans) < len(infos):
        return None
    total, (start, end) = 0.0, spans[0]
    for b, e in spans[1:]:
        if b > end:
            total, start = total + end - start, b
        end = max(end, e)
    return round(total + end - start, 3)


def data_stats(run_dir: Path) -> Path:
    """Per-frame point statistics of the SOTIF test data: count, max/mean range, ground share."""
    import pandas as pd
    from harness.core.kitti import frame_path, read_frames_meta, read_points
    data = run_dir / "data" / "sotif"
    meta = read_frames_meta(data / "meta" / "frames.csv")
    rows = []
    for fid in meta["frame_id"]:
        pts = read_points(frame_path(data, "velodyne", fid))
        rng = np.linalg.norm(pts[:, :2], axis=1)
        rows.append({"frame_id": fid, "n_points": len(pts), "max_range_m": float(rng.max()) if len(pts) else 0.0,
                     "mean_range_m": float(rng.mean()) if len(pts) else 0.0,
                     "ground_share": float((pts[:, 2] < -1.5).mean()) if len(pts) else 0.0,
                     "mean_intensity": float(pts[:, 3].mean()) if len(pts) else 0.0})
    from harness.cells import round_floats
    df = round_floats(meta[["frame_id", "split", "weather"]].merge(pd.DataFrame(rows), on="frame_id"))
    out = run_dir / "tables" / "data_stats.csv"
    atomic_write_text(out, df.to_csv(index=False, lineterminator="\n"))
    return out
