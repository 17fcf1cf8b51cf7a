"""KITTI-layout data set as :class:`harness.core.types.Sample` items (built on harness.core.kitti).

``KittiDataset(root, split, with_image=False, keep=False)``: frames listed in
``<root>/ImageSets/<split>.txt``; ``ds[i]`` reads velodyne points, calib and labels (converted to
LiDAR boxes) and, when ``with_image``, the left colour image as (3, H, W) float32 in [0, 1] with
``lidar2img``; with ``keep``, each frame is read from disk once (training's epochs).
``dataset_hash(root)`` fingerprints the data a model was trained on.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from harness.core import kitti
from harness.core.types import Sample


def split_file(root, split: str) -> Path:
    return Path(root) / "ImageSets" / f"{split}.txt"


def has_split(root, split: str) -> bool:
    """True when the split file exists and lists at least one frame."""
    path = split_file(root, split)
    return path.is_file() and bool(kitti.read_image_set(path))


KEEP_BYTES = 2 << 30  # frames a dataset with ``keep`` holds in memory: up to 2 GiB of arrays


class KittiDataset:
    """Frames of one split of a KITTI-layout folder. With ``keep`` (training: every epoch reads the
    same frames), the frames read are kept in memory, as long as they fit in ``KEEP_BYTES``, and
    returned again as the same :class:`Sample` (whose arrays the caller must not change in place). ``frame_ids``:
    the frames to read, in place of the split's list (e.g. every frame of a run's val set)."""

    def __init__(self, root, split: str = "train", with_image: bool = False, keep: bool = False,
                 frame_ids: list[str] | None = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise kitti.KittiError(self.root, "data folder not found")
        self.split = split
        self.with_image = with_image
        self.frame_ids = kitti.read_image_set(split_file(self.root, split)) if frame_ids is None else list(frame_ids)
        self._kept: dict[int, Sample] | None = {} if keep else None
        self._kept_bytes = 0

    def __len__(self) -> int:
        return len(self.frame_ids)

    def __getitem__(self, i: int) -> Sample:
        if self._kept is None:
            return self._read(i)
        if i in self._kept:
            return self._kept[i]
        sample = self._read(i)
        size = sum(a.nbytes for a in (sample.points, sample.gt_boxes, sample.image) if a is not None)
        if self._kept_bytes + size <= KEEP_BYTES:
            self._kept[i], self._kept_bytes = sample, self._kept_bytes + size
        return sample

    def _read(self, i: int) -> Sample:
        fid = self.frame_ids[i]
        points = kitti.read_points(kitti.frame_path(self.root, "velodyne", fid))
        calib = kitti.read_calib(kitti.frame_path(self.root, "calib", fid))
        labels = self.labels(i, calib)
        boxes = labels.to_lidar(calib) if len(labels) else np.zeros((0, 7), np.float32)
        image = lidar2img = None
        if self.with_image:
            image_path = kitti.frame_path(self.root, "image_2", fid)
            rgb = kitti.read_image(image_path)  # (H, W, 3) uint8
            kitti.check_image_fits_calib(image_path, rgb.shape[:2], calib, kitti.frame_path(self.root, "calib", fid))
            image = np.ascontiguousarray(rgb.transpose(2, 0, 1), dtype=np.float32) / 255.0
            lidar2img = calib.lidar2img().astype(np.float32)
        return Sample(fid, points, boxes, np.asarray(labels.name, dtype=str), image, lidar2img)

    def labels(self, i: int, calib: kitti.Calib | None = None) -> kitti.Labels:
        """Ground-truth labels of frame i (camera frame, as on disk), checked as ``evaluate`` checks them."""
        from harness.evaluate import check_ground_truth
        path = kitti.frame_path(self.root, "label_2", self.frame_ids[i])
        labels = kitti.read_labels(path)
        check_ground_truth(path, labels)
        return labels

    def calib(self, i: int) -> kitti.Calib:
        return kitti.read_calib(kitti.frame_path(self.root, "calib", self.frame_ids[i]))


def dataset_hash(root) -> str:
    """SHA-256 (16 hex) of meta/dataset.json when present, else of the split lists and labels."""
    root = Path(root)
    meta = root / "meta" / "dataset.json"
    h = hashlib.sha256()
    if meta.is_file():
        h.update(meta.read_bytes())
    else:
        for path in sorted((root / "ImageSets").glob("*.txt")) + sorted((root / "training" / "label_2").glob("*.txt")):
            h.update(path.name.encode())
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def config_hash(config: dict) -> str:
    """SHA-256 (16 hex) of a config dict in canonical JSON."""
    return hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()[:16]


def synthetic_sample(rng: np.random.Generator, num_cars: int = 3, extent: float = 14.0,
                     frame_id: str = "000000", density: float = 40.0) -> Sample:
    """A small synthetic frame for tests and smoke runs: a ground plane at z = -1.73 m and
    ``num_cars`` cars (4 x 1.7 x 1.5 m, random position in x 2..extent, |y| < 5, random yaw)
    whose points lie on the car surfaces (``density`` points per m^2)."""
    boxes = []
    while len(boxes) < num_cars:
        cand = np.array([rng.uniform(3, extent), rng.uniform(-5, 5), -0.98, rng.uniform(3.6, 4.4),
                         rng.uniform(1.6, 1.8), 1.5, rng.uniform(-np.pi, np.pi)], np.float32)
        if all(np.hypot(*(cand[:2] - b[:2])) > 5 for b in boxes):
            boxes.append(cand)
    ground = np.c_[rng.uniform(0, extent + 2, (600, 1)), rng.uniform(-8, 8, (600, 1)),
                   np.full((600, 1), -1.73), rng.uniform(0, 0.3, (600, 1))]
    parts = [ground]
    for b in boxes:
        parts.append(_surface_points(rng, b, density))
    points = np.concatenate(parts).astype(np.float32)
    boxes_arr = np.asarray(boxes, np.float32).reshape(-1, 7)
    return Sample(frame_id, points[rng.permutation(len(points))], boxes_arr, np.array(["Car"] * num_cars))


def _surface_points(rng: np.random.Generator, box: np.ndarray, density: float) -> np.ndarray:
    """(n, 4) points on the 4 sides and the top of a box (LiDAR frame), intensity 0.5..1."""
    x, y, z, l, w, h, yaw = box
    n = int(density * (2 * (l + w) * h + l * w))
    u = rng.uniform(-0.5, 0.5, (n, 3)) * [l, w, h]
    face = rng.integers(0, 5, n)
    u[face == 0, 0], u[face == 1, 0] = l / 2, -l / 2
    u[face == 2, 1], u[face == 3, 1] = w / 2, -w / 2
    u[face == 4, 2] = h / 2
    c, s = np.cos(yaw), np.sin(yaw)
    xy = np.c_[u[:, 0] * c - u[:, 1] * s + x, u[:, 0] * s + u[:, 1] * c + y]
    return np.c_[xy, u[:, 2] + z, rng.uniform(0.5, 1.0, n)]


def write_synthetic_dataset(root, frames: int, seed: int = 0, val: int = 0) -> Path:
    """A KITTI-layout folder of :func:`synthetic_sample` frames (train split + ``val`` frames)."""
    root = Path(root)
    calib = kitti.kitti_calib()
    ids = [f"{i:06d}" for i in range(frames)]
    for i, fid in enumerate(ids):
        sample = synthetic_sample(np.random.default_rng([seed, i]), frame_id=fid)
        kitti.write_points(kitti.frame_path(root, "velodyne", fid), sample.points)
        kitti.write_calib(kitti.frame_path(root, "calib", fid), calib)
        kitti.write_labels(kitti.frame_path(root, "label_2", fid),
                           kitti.Labels.from_lidar(sample.gt_boxes, calib, sample.gt_names))
    kitti.write_image_set(root / "ImageSets" / "train.txt", ids[: frames - val])
    kitti.write_image_set(root / "ImageSets" / "val.txt", ids[frames - val:])
    return root
