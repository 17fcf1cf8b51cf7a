"""Generate a KITTI-layout data set: the SOTIF scenario per weather, or training scenes.

Layout (docs/simulator.md): <out>/training/{velodyne,image_2,calib,label_2}/NNNNNN.*,
<out>/ImageSets/{train,val,test}.txt, <out>/meta/frames.csv, <out>/meta/dataset.json.
Each frame also leaves meta/frames/NNNNNN.json (its meta row and file hashes); a re-run
skips frames whose record, config and file hashes match (resume). dataset.json is last.
The test frames also appear in the views of ``simulator.toolkit_views`` (symlinks) for
OpenPCDet's and MMDetection3D's stock KITTI tools.
"""
from __future__ import annotations

import ctypes
import hashlib
import json
import multiprocessing as mp
import sys
import threading
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from harness.core import kitti
from harness.core.files import atomic_write_text, folder_lock, remove_temp_files, sha256_file
from simulator.camera import CameraSpec
from simulator.frame import FrameJob, instance_run, make_frame, row_columns
from simulator.labels import LabelConfig
from simulator.lidar import LidarSpec, carla_spec
from simulator.road import RoadConfig
from simulator.bounds import check_probes
from simulator.scenario import SotifConfig, TrainConfig, instance_steps
from simulator.space import SWEEP_WEATHER, ScenarioSpace, check_space, instances, val_instances
from simulator.toolkit_views import write_views
from simulator.weather import DRY_PRESETS, WEATHER_PRESETS

GENERATOR_VERSION = "1.8"  # bump whenever the same seed gives other bytes
PRESETS = ("sotif", "train", "sweep", "bounds")
INSTANCE_PRESETS = ("sweep", "bounds")  # a set of instances under weathers of their own (weather "Sweep")
LIDAR_MODELS = ("physics", "carla")
SOTIF_FRAMES, SOTIF_VAL = 547, 55
TRAIN_FRAMES, TRAIN_VAL_SHARE = 400, 0.15


@dataclass(frozen=True)
class GenerateConfig:
    """Everything that determines the bytes of the data set."""

    preset: str
    frames: int
    weathers: tuple[str, ...]
    seed: int
    lidar: LidarSpec
    camera: CameraSpec = CameraSpec()
    road: RoadConfig = RoadConfig()
    labels: LabelConfig = LabelConfig()
    sotif: SotifConfig = SotifConfig()
    train: TrainConfig = TrainConfig()
    generator_version: str = GENERATOR_VERSION
    space: ScenarioSpace | None = None  # instance mode (simulator.space); None: the study's protocol / training

    def as_dict(self) -> dict:
        """The config as JSON data; without instance mode it has no "space" key (the bytes of earlier sets)."""
        d = json.loads(json.dumps(asdict(self)))
        if d["space"] is None:
            del d["space"]
        elif not d["space"]["probes"]:  # the bytes of sets made before bounds sets existed
            del d["space"]["probes"]
        return d

    def digest(self) -> str:
        return hashlib.sha256(json.dumps(self.as_dict(), sort_keys=True).encode()).hexdigest()


def _check_instances(preset, instances, frames, weathers, val_share: float | None = None,
                     probes=None) -> ScenarioSpace | None:
    """The instance mode's space (None: the study's protocol or training scenes); ValueError naming a bad input."""
    if (preset == "bounds") != (probes is not None):
        raise ValueError("probes go with the bounds preset, and the bounds preset needs probes")
    if preset == "bounds":
        if frames is not None or weathers is not None or instances != 1:
            raise ValueError("a bounds set takes neither frames, weathers nor instances: one instance per probe")
        probes = check_probes(probes)
        # every frame test; no lead-in: the verdict reads the frames from the lane change on
        return ScenarioSpace(len(probes), sweep=True, probes=probes, val_share=0.0, lead_in_frames=0)
    if not isinstance(instances, (int, np.integer)) or isinstance(instances, bool) or instances < 1:
        raise ValueError(f"instances must be an integer >= 1, got {instances!r}")
    if preset == "train" and instances != 1:
        raise ValueError(f"instances applies to the sotif and sweep presets, not to train (got {instances})")
    if preset != "sweep" and instances == 1:
        return None
    if frames is not None:
        raise ValueError("frames cannot be set with instances > 1 or the sweep preset: each instance records "
                         "its own frames")
    if preset == "sweep" and weathers is not None:
        raise ValueError("weathers cannot be set with the sweep preset: it draws its own weather per instance")
    if val_share is not None and not (isinstance(val_share, (int, float)) and 0.0 <= val_share < 1.0):
        raise ValueError(f"val_share must be a number in [0, 1), got {val_share!r}")
    space = ScenarioSpace(int(instances), sweep=preset == "sweep")
    space = space if val_share is None else replace(space, val_share=float(val_share))
    check_space(space)
    return space


def _check_args(preset, frames, weathers, workers, lidar_model) -> tuple[str, ...]:
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; valid: {', '.join(PRESETS)}")
    if preset in INSTANCE_PRESETS:
        weathers = [SWEEP_WEATHER]
    if lidar_model not in LIDAR_MODELS:
        raise ValueError(f"unknown lidar model {lidar_model!r}; valid: {', '.join(LIDAR_MODELS)}")
    if frames is not None and (not isinstance(frames, (int, np.integer)) or isinstance(frames, bool) or frames < 1):
        raise ValueError(f"frames must be an integer >= 1, got {frames!r}")
    if not isinstance(workers, (int, np.integer)) or isinstance(workers, bool) or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    if isinstance(weathers, str):
        weathers = [w.strip() for w in weathers.split(",") if w.strip()]
    if weathers is None:
        weathers = list(WEATHER_PRESETS) if preset == "sotif" else list(DRY_PRESETS)
    if len(weathers) == 0:
        raise ValueError("weathers must name at least one preset")
    bad = [w for w in weathers if w not in WEATHER_PRESETS and preset not in INSTANCE_PRESETS]
    if bad:
        raise ValueError(f"unknown weather preset(s) {', '.join(map(repr, bad))}; valid: {', '.join(WEATHER_PRESETS)}")
    if len(set(weathers)) != len(weathers):
        raise ValueError(f"weathers lists a preset twice: {weathers}")
    return tuple(weathers)


def default_frames(preset: str, n_weathers: int) -> int:
    """547 SOTIF frames over the 21 presets (~26 per run, like the paper), or 400 training scenes."""
    return int(round(SOTIF_FRAMES * n_weathers / len(WEATHER_PRESETS))) if preset == "sotif" else TRAIN_FRAMES


def max_frames(preset: str, n_weathers: int) -> int | float:
    """`frames` only caps the SOTIF set: a run records at most the scenario's length."""
    return default_frames(preset, n_weathers) if preset == "sotif" else float("inf")


def _spread(total: int, n: int) -> list[int]:
    """`total` split over n parts as evenly as possible, the first parts one larger."""
    return [total // n + (1 if i < total % n else 0) for i in range(n)]


def plan_instance_jobs(cfg: GenerateConfig) -> list[FrameJob]:
    """Instance mode: per weather (in order) its instances (in order), each with the frames of
    scenario.instance_steps; whole instances in val (space.val_share, never instance 0), the rest test."""
    sp = cfg.space
    val = val_instances(sp.instances, sp.val_share)
    per_instance = []  # (recorded (step, in window), steps of the run) per instance
    for i, inst in enumerate(instances(sp, cfg.seed)):
        run = instance_run(cfg, i)
        per_instance.append((instance_steps(run, inst.sotif_config(cfg.sotif), sp.lead_in_frames, sp.window_slack_s,
                                            sp.window_max_s), len(run)))
    specs = [(w, i, k, win, per_instance[i][1]) for w in cfg.weathers for i in range(sp.instances)
             for k, win in per_instance[i][0]]
    return [FrameJob(n, f"{n:06d}", w, k, "val" if i in val else "test", length, i, win)
            for n, (w, i, k, win, length) in enumerate(specs)]


def plan_jobs(cfg: GenerateConfig) -> list[FrameJob]:
    """Frame jobs in frame-id order with their split.

    SOTIF: a capped set keeps each weather's frames spread over the whole scenario run.
    """
    if cfg.space is not None:
        return plan_instance_jobs(cfg)
    if cfg.preset == "sotif":
        n_w = len(cfg.weathers)
        full = _spread(default_frames("sotif", n_w), n_w)  # recorded steps of a whole run
        specs = [(w, int(k)) for w, c, f in zip(cfg.weathers, _spread(cfg.frames, n_w), full)
                 for k in np.linspace(0, f - 1, c).round()] if cfg.frames else []
        n_val = int(round(cfg.frames * SOTIF_VAL / SOTIF_FRAMES))
        other = "test"
    else:
        specs = [(cfg.weathers[i % len(cfg.weathers)], i) for i in range(cfg.frames)]
        n_val = int(round(cfg.frames * TRAIN_VAL_SHARE))
        other = "train"
    val = set(np.unique(np.linspace(0, cfg.frames - 1, n_val).round().astype(int)).tolist()) if n_val else set()
    max_step = max((k for _, k in specs), default=0) + 1
    return [FrameJob(i, f"{i:06d}", w, k, "val" if i in val else other, max_step) for i, (w, k) in enumerate(specs)]


def content_digest(files: dict[str, str]) -> str:
    """SHA-256 over the sorted (relative path, file SHA-256) pairs of a data set: its identity. Two sets
    with this digest equal hold the same bytes (meta/dataset.json, which carries it, is not among them)."""
    lines = "".join(f"{rel}\0{files[rel]}\n" for rel in sorted(files))
    return hashlib.sha256(lines.encode()).hexdigest()


def read_content_digest(root: Path) -> str | None:
    """The content digest meta/dataset.json records (computed from its file list for a set written before
    the digest was recorded); None without a readable meta/dataset.json."""
    try:
        meta = json.loads((Path(root) / "meta" / "dataset.json").read_text())
        return meta.get("content_sha256") or content_digest(meta["files"])
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def _record_path(root: Path, frame_id: str) -> Path:
    return root / "meta" / "frames" / f"{frame_id}.json"


def _resumable(root: Path, job: FrameJob, digest: str) -> dict | None:
    """The stored frame record if its config and file hashes all match the files on disk."""
    rec_path = _record_path(root, job.frame_id)
    try:
        rec = json.loads(rec_path.read_text())
    except (OSError, ValueError):
        return None
    if rec.get("config") != digest or rec.get("row", {}).get("split") != job.split:
        return None
    for rel, digest_file in rec.get("files", {}).items():
        p = root / rel
        if not p.is_file() or sha256_file(p) != digest_file:
            return None
    return rec


def remove_stale_frames(root: Path, frame_ids: set[str]) -> int:
    """Delete the frames an earlier generation into ``root`` made that this one does not plan
    (e.g. it asks for fewer frames): the files its frame records list, then the records. Files
    no record lists are left alone. Returns the number of frames removed."""
    removed = 0
    for rec_path in sorted((root / "meta" / "frames").glob("*.json")):
        if rec_path.stem in frame_ids:
            continue
        try:
            files = json.loads(rec_path.read_text()).get("files", {})
        except (OSError, ValueError, AttributeError):
            continue  # not a record of ours
        for rel in files:
            p = (root / rel).resolve()
            if p.parent.parent == (root / "training").resolve() and p.stem == rec_path.stem:
                p.unlink(missing_ok=True)
        rec_path.unlink()
        removed += 1
    return removed


def _stored_config(root: Path) -> tuple[set[str], dict | None]:
    """The config digests that ``root``'s meta/dataset.json and frame records name (unreadable ones
    skipped: a damaged record's frame is made again), and the config meta/dataset.json holds."""
    digests, config = set(), None
    try:
        meta = json.loads((root / "meta" / "dataset.json").read_text())
        digests.add(meta["config_sha256"])
        config = meta.get("config")
    except (OSError, ValueError, LookupError, TypeError, AttributeError):
        pass
    for rec_path in sorted((root / "meta" / "frames").glob("*.json")):
        try:
            digests.add(json.loads(rec_path.read_text())["config"])
        except (OSError, ValueError, LookupError, TypeError):
            pass
    return digests, config


def _first_foreign_file(root: Path, frame_ids: set[str]) -> Path | None:
    """A file in ``root`` that a generation of ``frame_ids`` cut short before its first frame record
    cannot have left (it leaves only the files of its frames, temp files included, and meta/frames/)."""
    for top in sorted(root.iterdir()):
        if top.name == ".lock" and top.is_file():  # a simulate's folder lock
            continue
        if top.name not in ("meta", "training") or top.is_symlink() or not top.is_dir():
            return top
    for path in sorted(root.rglob("*")):
        if path.is_dir() and not path.is_symlink():
            continue
        rel = path.relative_to(root).parts
        frame_file = rel[0] == "training" and len(rel) == 3 and path.name.lstrip(".").split(".")[0] in frame_ids
        if not (frame_file or rel[:2] == ("meta", "frames")):
            return path
    return None


def _config_change(old: dict | None, cfg: GenerateConfig) -> str:
    """What differs between a stored config and ``cfg``, for a message."""
    if not isinstance(old, dict):
        return "its frame records name another configuration"
    new = cfg.as_dict()
    changed = [f"{key} differs" if isinstance(new[key], (dict, list)) else f"{key} {old.get(key)} (asked {new[key]})"
               for key in new if old.get(key) != new[key]]
    return ", ".join(changed) or "its frame records name another configuration"


def check_output(root: Path, cfg: GenerateConfig, frame_ids: set[str], force: bool = False) -> None:
    """Refuse (ValueError, nothing changed) to write the data set of ``cfg`` into ``root`` when it holds
    anything but a data set of this same configuration, whole or partial: a data set of another
    configuration, or other files. ``force``: no check (the data set is written over what is there)."""
    if root.exists() and not root.is_dir():
        raise ValueError(f"{root}: output path exists and is not a directory")
    if force or not root.exists():
        return
    digests, config = _stored_config(root)
    how = "pass --force to replace it, or choose another output folder"
    if digests - {cfg.digest()}:
        raise ValueError(f"{root}: holds a data set simulated with another configuration "
                         f"({_config_change(config, cfg)}); refusing to replace it ({how})")
    if digests:
        return  # this configuration's data set: resumed, or kept as it is
    foreign = _first_foreign_file(root, frame_ids)
    if foreign is not None:
        raise ValueError(f"{root}: is not empty and holds no data set of this configuration (it has "
                         f"{foreign.relative_to(root)}); refusing to write into it ({how})")


def run_job(args) -> dict:
    """Make (or resume) one frame; returns its record {"config", "row", "files": {path: sha256}}."""
    root, cfg, job, digest = args
    rec = _resumable(root, job, digest)
    if rec is not None:
        return rec
    row, files = make_frame(root, cfg, job)
    rec = {"config": digest, "row": row, "files": {str(p.relative_to(root)): sha256_file(p) for p in files}}
    atomic_write_text(_record_path(root, job.frame_id), json.dumps(rec, indent=1, sort_keys=True))
    return rec


def _write_outputs(root: Path, cfg: GenerateConfig, records: list[dict]) -> None:
    rows = sorted((r["row"] for r in records), key=lambda r: r["frame_id"])
    df = pd.DataFrame(rows, columns=list(row_columns(cfg)))
    written = [kitti.write_image_set(root / "ImageSets" / f"{split}.txt",
                                     df.loc[df["split"] == split, "frame_id"].tolist()) for split in ("train", "val", "test")]
    write_views(root, df.loc[df["split"] == "test", "frame_id"].tolist(),  # for OpenPCDet / MMDetection3D
                df["frame_id"].tolist(), cfg.lidar.mount_height)
    written.append(kitti.write_frames_meta(root / "meta" / "frames.csv", df))
    files = {rel: h for r in records for rel, h in r["files"].items()}
    files.update({str(p.relative_to(root)): sha256_file(p) for p in written})
    meta = {"generator": "sotif-bench simulator", "generator_version": cfg.generator_version, "seed": cfg.seed,
            "config": cfg.as_dict(), "config_sha256": cfg.digest(), "sensors": {"lidar": cfg.lidar.as_dict(),
            "camera": cfg.camera.as_dict()}, "n_frames": len(df),
            "splits": {s: int((df["split"] == s).sum()) for s in ("train", "val", "test")},
            "files": dict(sorted(files.items())), "content_sha256": content_digest(files)}
    atomic_write_text(root / "meta" / "dataset.json", json.dumps(meta, indent=1, sort_keys=True) + "\n")


def start_method() -> str:
    """How the simulation's worker processes start: "fork" (no re-import, the quickest) from a process that
    runs no other Python thread and has loaded neither torch nor onnxruntime (the command line's `simulate`);
    else "spawn". From a `run` process after its model jobs and runtime probes (the job pool's, tqdm's and the
    runtimes' threads) a forked worker can inherit a lock another thread held at the fork and wait on it for
    ever: the boundary searches' simulation did, after 62 of 497 frames. Spawned workers make the same bytes."""
    if "fork" not in mp.get_all_start_methods():
        return "spawn"
    threaded = threading.active_count() > 1 or any(m in sys.modules for m in ("torch", "onnxruntime"))
    return "spawn" if threaded else "fork"


def worker_init() -> None:
    """Keep freed buffers in the worker's heap (glibc): a scan allocates dozens of MB-sized
    temporaries, and returning each to the OS costs page faults on the next frame (~10 % of
    a frame). Only the worker processes this module starts are tuned; elsewhere a no-op."""
    try:
        libc = ctypes.CDLL(None)
        libc.mallopt(-3, 1 << 29)  # M_MMAP_THRESHOLD: 512 MB
        libc.mallopt(-1, 1 << 30)  # M_TRIM_THRESHOLD: 1 GB
    except (OSError, AttributeError):
        pass


def generate(out: Path, preset: str = "sotif", frames: int | None = None, weathers: list[str] | None = None,
             seed: int = 0, workers: int = 1, lidar_model: str = "physics", progress: bool = True,
             lidar_spec: LidarSpec | None = None, force: bool = False, instances: int = 1,
             val_share: float | None = None, probes=None) -> Path:
    """Write the data set to `out` and return `out`. ValueError on invalid arguments.

    A partial data set of the same configuration in `out` is resumed, a whole one kept; anything
    else there (a data set of another configuration, other files) is refused unless `force`, which
    writes the data set over it (the frames an earlier generation recorded and this one does not
    plan are removed; files of no record stay).

    `lidar_spec` replaces the HDL-64E-like default sensor (its `model` is then set from
    `lidar_model`, "carla" turning it into CARLA's weather-blind ray-cast LiDAR).

    `instances`: 1 with preset "sotif" is the study's protocol (one scripted run per weather, every 5th
    step). More, or preset "sweep", is instance mode (simulator.space): N instances per weather (sweep: N
    in all, weather drawn per instance), each recorded around its decision window; `frames` is then unset.
    `val_share` (instance mode): the share of each weather's instances in the val split (default
    ScenarioSpace.val_share; 0: every instance is test, as `run` makes them: its own val set picks the
    operating thresholds).
    `probes` (preset "bounds" only): the ``simulator.bounds.Probe`` instances of a controlled sweep, one
    instance each, every frame test.
    """
    asked_weathers = weathers
    weathers = _check_args(preset, frames, weathers, workers, lidar_model)
    space = _check_instances(preset, instances, frames, asked_weathers, val_share, probes)
    if space is not None:
        frames = 0  # each instance records its own frames
    elif frames is None:
        frames = default_frames(preset, len(weathers))
    else:
        frames = min(frames, max_frames(preset, len(weathers)))
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    base = lidar_spec if lidar_spec is not None else LidarSpec()
    lidar = replace(base, model="physics") if lidar_model == "physics" else carla_spec(base)
    cfg = GenerateConfig(preset, int(frames), weathers, int(seed), lidar, space=space)
    root = Path(out)
    digest = cfg.digest()
    jobs = [(root, cfg, job, digest) for job in plan_jobs(cfg)]
    planned = {job.frame_id for _, _, job, _ in jobs}
    check_output(root, cfg, planned, force)
    (root / "meta" / "frames").mkdir(parents=True, exist_ok=True)
    with folder_lock(root, "simulate"):  # one simulate per folder: the temp files below are its own
        remove_temp_files(root)  # those a killed simulate left
        remove_stale_frames(root, planned)
        _simulate_frames(root, cfg, preset, jobs, workers, progress)
    return root


def _simulate_frames(root: Path, cfg: GenerateConfig, preset: str, jobs: list, workers: int, progress: bool) -> None:
    bar = tqdm(total=len(jobs), desc=f"simulate {preset}", unit="frame", disable=not progress)
    records = []
    if workers == 1:
        for args in jobs:
            records.append(run_job(args))
            bar.update()
    else:
        chunk = max(1, len(jobs) // (workers * 8))
        with mp.get_context(start_method()).Pool(workers, initializer=worker_init) as pool:
            for rec in pool.imap_unordered(run_job, jobs, chunksize=chunk):
                records.append(rec)
                bar.update()
    bar.close()
    _write_outputs(root, cfg, records)
