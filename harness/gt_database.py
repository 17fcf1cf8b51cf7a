"""Ground-truth database sampling ("copy-paste" augmentation of SECOND / OpenPCDet ``gt_sampling``,
MMDetection3D ``ObjectSample``).

``build_database(root)`` collects, from the training split of a KITTI folder, every labelled object
of the chosen classes with the points inside its box (LiDAR frame, where they were recorded), its
box, class, frame id, point count and KITTI difficulty, keeping those with enough points.
``load_or_build(root, cache)`` keeps it in one ``.npz`` file keyed by a fingerprint of the data
and of the database settings: a missing, corrupt or mismatching cache is rebuilt, never trusted.

``sample_objects(sample, db, rng)`` pastes database objects into a frame at their recorded place:
up to ``sample_groups`` objects of a class per frame, each rejected when its BEV box overlaps a box
of the frame or an already accepted one (rotated BEV IoU > 0); the frame's points inside accepted
boxes are removed before the objects' points are added.
"""
from __future__ import annotations

import hashlib
import io
import json
import zipfile
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numba
import numpy as np

from harness.core import kitti
from harness.core.boxes import iou_bev, points_in_boxes
from harness.core.files import atomic_write_bytes
from harness.core.types import Sample
from harness.dataset import KittiDataset

FORMAT = "sotif.gt_database.1"
_FIELDS = ("points", "offsets", "boxes", "names", "frame_ids", "num_points", "difficulty")


@dataclass(frozen=True)
class GtSamplingConfig:
    enabled: bool = True
    classes: tuple[str, ...] = ("Car",)  # classes collected into the database
    min_points: int = 5  # OpenPCDet filter_by_min_points Car:5
    difficulties: tuple[int, ...] | None = None  # KITTI levels kept (0 easy .. 2 hard, -1 none); None = all
    sample_groups: tuple[tuple[str, int], ...] = (("Car", 15),)  # target boxes of a class per frame
    skip_own_frame: bool = True  # never paste an object back into the frame it came from


@dataclass
class GtDatabase:
    """Objects of a data set; the points of object i are ``points[offsets[i]:offsets[i + 1]]``."""

    points: np.ndarray  # (P, 4) float32, LiDAR frame of the source frame
    offsets: np.ndarray  # (n + 1,) int64
    boxes: np.ndarray  # (n, 7) float32
    names: np.ndarray  # (n,) str
    frame_ids: np.ndarray  # (n,) str
    num_points: np.ndarray  # (n,) int64
    difficulty: np.ndarray  # (n,) int64, KITTI 0 easy / 1 moderate / 2 hard / -1 none

    def __len__(self) -> int:
        return len(self.boxes)

    def object_points(self, i: int) -> np.ndarray:
        return self.points[self.offsets[i]:self.offsets[i + 1]]


def kitti_difficulty(labels: kitti.Labels) -> np.ndarray:
    """(K,) KITTI difficulty: the easiest level whose height / occlusion / truncation limits hold."""
    height = labels.bbox[:, 3] - labels.bbox[:, 1]
    out = np.full(len(labels), -1, np.int64)
    for level, (min_h, max_occ, max_trunc) in reversed(list(enumerate([(40, 0, 0.15), (25, 1, 0.30),
                                                                        (25, 2, 0.50)]))):
        ok = (height >= min_h) & (labels.occluded <= max_occ) & (labels.truncated <= max_trunc)
        out[ok] = level
    return out


def _collect(ds: KittiDataset, cfg: GtSamplingConfig) -> GtDatabase:
    parts, boxes, names, fids, diffs = [], [], [], [], []
    for i in range(len(ds)):
        sample = ds[i]
        keep = np.isin(sample.gt_names, cfg.classes)
        if not keep.any():
            continue
        difficulty = kitti_difficulty(ds.labels(i))[keep]
        inside = points_in_boxes(sample.points, sample.gt_boxes[keep])  # (N, k)
        for j, box in enumerate(sample.gt_boxes[keep]):
            parts.append(sample.points[inside[:, j]])
            boxes.append(box)
            names.append(sample.gt_names[keep][j])
            fids.append(sample.frame_id)
            diffs.append(difficulty[j])
    counts = np.array([len(p) for p in parts], np.int64)
    return GtDatabase(points=np.concatenate(parts).astype(np.float32) if parts else np.zeros((0, 4), np.float32),
                      offsets=np.r_[0, np.cumsum(counts)].astype(np.int64),
                      boxes=np.asarray(boxes, np.float32).reshape(-1, 7), names=np.asarray(names, dtype=str),
                      frame_ids=np.asarray(fids, dtype=str), num_points=counts,
                      difficulty=np.asarray(diffs, np.int64))


def select(db: GtDatabase, mask: np.ndarray) -> GtDatabase:
    """The objects where ``mask`` is true."""
    idx = np.flatnonzero(mask)
    counts = db.num_points[idx]
    points = [db.object_points(i) for i in idx]
    return GtDatabase(points=np.concatenate(points) if points else np.zeros((0, 4), np.float32),
                      offsets=np.r_[0, np.cumsum(counts)].astype(np.int64), boxes=db.boxes[idx],
                      names=db.names[idx], frame_ids=db.frame_ids[idx], num_points=counts,
                      difficulty=db.difficulty[idx])


def build_database(root, cfg: GtSamplingConfig = GtSamplingConfig(), split: str = "train") -> GtDatabase:
    """Objects of ``cfg.classes`` in ``split`` with at least ``cfg.min_points`` points (and a kept
    difficulty when ``cfg.difficulties`` is set)."""
    db = _collect(KittiDataset(root, split), cfg)
    mask = db.num_points >= cfg.min_points
    if cfg.difficulties is not None:
        mask &= np.isin(db.difficulty, cfg.difficulties)
    return select(db, mask)


def data_key(root, cfg: GtSamplingConfig, split: str = "train") -> str:
    """SHA-256 (16 hex) of the split's frame list, label and velodyne files (name, size, mtime),
    meta/dataset.json and the database settings."""
    root = Path(root)
    h = hashlib.sha256(FORMAT.encode())
    h.update(json.dumps({k: v for k, v in asdict(cfg).items() if k in ("classes", "min_points", "difficulties")},
                        sort_keys=True).encode())
    h.update(f"{split}\n".encode())
    meta = root / "meta" / "dataset.json"
    if meta.is_file():
        h.update(meta.read_bytes())
    for fid in kitti.read_image_set(root / "ImageSets" / f"{split}.txt"):
        h.update(fid.encode())
        h.update(kitti.frame_path(root, "label_2", fid).read_bytes())
        st = kitti.frame_path(root, "velodyne", fid).stat()
        h.update(f"{st.st_size} {st.st_mtime_ns}".encode())
    return h.hexdigest()[:16]


def save(path, db: GtDatabase, key: str) -> Path:
    """Write the database with its key to ``path`` (.npz) atomically."""
    buf = io.BytesIO()
    np.savez(buf, key=np.array(key), **{f: getattr(db, f) for f in _FIELDS})
    return atomic_write_bytes(path, buf.getvalue())


def load(path, key: str) -> GtDatabase:
    """The database stored at ``path``; ``ValueError`` naming the file when it is unreadable,
    inconsistent or was built for another key."""
    try:
        with np.load(path, allow_pickle=False) as z:
            stored = str(z["key"])
            arrays = {f: z[f] for f in _FIELDS}
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise ValueError(f"{path}: unreadable ground-truth database ({e})") from e
    if stored != key:
        raise ValueError(f"{path}: built for data key {stored}, expected {key}")
    db = GtDatabase(**arrays)
    n = len(db.boxes)
    ok = (db.points.ndim == 2 and db.points.shape[1] == 4 and db.boxes.shape == (n, 7)
          and all(len(a) == n for a in (db.names, db.frame_ids, db.num_points, db.difficulty))
          and len(db.offsets) == n + 1 and db.offsets[0] == 0 and db.offsets[-1] == len(db.points)
          and np.array_equal(np.diff(db.offsets), db.num_points))
    if not ok:
        raise ValueError(f"{path}: inconsistent ground-truth database arrays")
    return db


def load_or_build(root, cache_dir, cfg: GtSamplingConfig = GtSamplingConfig(), split: str = "train") -> GtDatabase:
    """The database of ``root``'s ``split``, from ``<cache_dir>/gt_database_<split>.npz`` when that
    was built from the same data and settings, else built and cached (when the folder is writable)."""
    key = data_key(root, cfg, split)
    path = Path(cache_dir) / f"gt_database_{split}.npz"
    if path.is_file():
        try:
            return load(path, key)
        except ValueError:
            pass  # stale or corrupt: rebuild below
    db = build_database(root, cfg, split)
    try:
        save(path, db, key)
    except OSError:
        pass  # read-only data folder: use the database without caching it
    return db


@numba.njit(cache=True)
def _any_box_kernel(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(N,) bool: point inside at least one box (boundary included); float64 as points_in_boxes."""
    out = np.zeros(points.shape[0], np.bool_)
    reach = np.sqrt(boxes[:, 3] ** 2 + boxes[:, 4] ** 2) / 2  # BEV radius around the centre
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    for n in range(points.shape[0]):
        for k in range(boxes.shape[0]):
            dx, dy = points[n, 0] - boxes[k, 0], points[n, 1] - boxes[k, 1]
            if abs(dx) > reach[k] or abs(dy) > reach[k]:
                continue
            dz = points[n, 2] - boxes[k, 2]
            if (abs(dx * c[k] + dy * s[k]) <= boxes[k, 3] / 2 and abs(-dx * s[k] + dy * c[k]) <= boxes[k, 4] / 2
                    and abs(dz) <= boxes[k, 5] / 2):
                out[n] = True
                break
    return out


def in_any_box(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(N,) bool: point inside any of the boxes (K, 7); ``points_in_boxes(...).any(1)`` without the
    (N, K) intermediates."""
    pts = np.ascontiguousarray(np.asarray(points)[:, :3], dtype=np.float64)
    return _any_box_kernel(pts, np.ascontiguousarray(np.asarray(boxes, dtype=np.float64).reshape(-1, 7)))


def _draw(db: GtDatabase, sample: Sample, cfg: GtSamplingConfig, rng: np.random.Generator) -> np.ndarray:
    """Indices of candidate objects: per class, as many as the frame lacks to reach its target."""
    picks = []
    for name, target in cfg.sample_groups:
        want = target - int(np.sum(sample.gt_names == name))
        pool = np.flatnonzero((db.names == name) & ~(cfg.skip_own_frame & (db.frame_ids == sample.frame_id)))
        if want > 0 and len(pool):
            picks.append(rng.choice(pool, size=min(want, len(pool)), replace=False))
    return np.concatenate(picks) if picks else np.zeros(0, np.int64)


def sample_objects(sample: Sample, db: GtDatabase, rng: np.random.Generator,
                   cfg: GtSamplingConfig = GtSamplingConfig()) -> Sample:
    """``sample`` with database objects pasted in (see the module docstring); unchanged when the
    database is empty or no candidate fits."""
    cand = _draw(db, sample, cfg, rng)
    if len(cand) == 0:
        return sample
    existing = sample.gt_boxes.reshape(-1, 7)
    iou = iou_bev(db.boxes[cand], np.concatenate([existing, db.boxes[cand]]))  # (c, K + c)
    free = iou[:, :len(existing)].max(axis=1, initial=0.0) <= 0
    accepted: list[int] = []
    for j in range(len(cand)):
        if free[j] and not (iou[j, len(existing) + np.asarray(accepted, np.int64)] > 0).any():
            accepted.append(j)
    if not accepted:
        return sample
    chosen = cand[accepted]
    boxes = db.boxes[chosen]
    outside = ~in_any_box(sample.points, boxes)
    points = np.concatenate([sample.points[outside]] + [db.object_points(i) for i in chosen])
    return replace(sample, points=points.astype(np.float32),
                   gt_boxes=np.concatenate([existing, boxes]).astype(np.float32),
                   gt_names=np.concatenate([sample.gt_names.astype(str), db.names[chosen]]))
