"""Views of a data set for OpenPCDet's and MMDetection3D's stock KITTI info generation (docs/kitti_tools.md).

Both toolkits read the split named ``test`` from ``testing/`` and the others from ``training/``,
and only ``train`` and ``val`` get labelled infos. Our labelled test frames live in ``training/``
(ImageSets/test.txt), so the data set gets two views made of relative symlinks to its own files:

- ``testing/{velodyne,image_2,calib}/NNNNNN.*``: the test frames where the stock tools look for
  them (no labels, as KITTI's testing set), so ``create_kitti_infos`` runs on ``<root>``;
- ``test_as_val/``: a KITTI root whose ``val`` split is our test split (``training/`` holds links
  to those frames, labels included; ``train`` and ``test`` are empty), so a stock config pointed at
  ``<root>/test_as_val`` evaluates the labelled test frames as its validation set;
- ``training/planes/NNNNNN.txt``: each frame's road plane in KITTI's planes format (rectified camera
  frame, ``a x + b y + c z + d = 0``, line 4 of the file), which OpenPCDet's ground-truth sampler
  reads when ``USE_ROAD_PLANE`` is on (its stock KITTI config): without the file its
  ``data_dict['road_plane']`` raises KeyError during training. The highway is flat, so the plane is
  the road ``z = -mount_height`` in the LiDAR frame, carried into the camera frame by the frame's calib.

Each link is made under a temp name and renamed into place; links the data set no longer plans
are removed (regular files in the views are never touched). The same data set gives the same links.
Plane files are written atomically; ``planes/`` holds one per frame of the data set, no others.
"""
from __future__ import annotations

import os
import secrets
from pathlib import Path

import numpy as np

from harness.core import kitti
from harness.core.files import atomic_write_text

TESTING_KINDS = ("velodyne", "image_2", "calib")
VIEW_ROOT = "test_as_val"
PLANES = "planes"


def road_plane(calib: kitti.Calib, mount_height: float) -> np.ndarray:
    """(a, b, c, d), unit normal pointing up (b < 0: the camera's y axis points down), of the road
    ``z = -mount_height`` (LiDAR frame) in the rectified camera frame: a x + b y + c z + d = 0."""
    m = calib.velo_to_rect()
    normal = m[:3, :3] @ np.array([0.0, 0.0, 1.0])  # a rotation keeps the unit length
    return np.append(normal, mount_height - normal @ m[:3, 3])


def plane_text(plane: np.ndarray) -> str:
    """KITTI's planes file: three header lines, then the four coefficients."""
    return "# Plane\nWidth 4\nHeight 1\n" + " ".join(f"{v:.6e}" for v in plane) + "\n"


def write_planes(root: Path, ids: list[str], mount_height: float) -> None:
    """``root/training/planes/`` holds exactly one plane file per frame of ``ids``."""
    folder = Path(root) / "training" / PLANES
    folder.mkdir(parents=True, exist_ok=True)
    wanted = {f"{i}.txt" for i in ids}
    for p in folder.glob("*.txt"):
        if p.name not in wanted and not p.is_symlink():
            p.unlink()
    for fid in ids:
        text = plane_text(road_plane(kitti.read_calib(kitti.frame_path(root, "calib", fid)), mount_height))
        path = folder / f"{fid}.txt"
        if not path.is_file() or path.read_text() != text:
            atomic_write_text(path, text)


def _link(path: Path, target: str) -> None:
    """Make ``path`` a symlink to ``target`` (relative), replacing any other link atomically."""
    if path.is_symlink() and os.readlink(path) == target:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}.tmp"
    os.symlink(target, tmp)
    try:
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _sync_links(folder: Path, wanted: dict[str, str]) -> None:
    """``folder`` holds exactly the symlinks ``wanted`` (name -> target); other symlinks are removed."""
    if folder.is_dir():
        for p in folder.iterdir():
            if p.is_symlink() and p.name not in wanted:
                p.unlink()
    for name, target in sorted(wanted.items()):
        _link(folder / name, target)


def _frame_links(ids: list[str], kind: str, depth: int) -> dict[str, str]:
    """Link name -> relative target of each frame's ``kind`` file, from a folder ``depth`` levels below the root."""
    ext = kitti.KINDS[kind]
    return {f"{i}{ext}": str(Path(*[".."] * depth, "training", kind, f"{i}{ext}")) for i in ids}


def write_views(root: Path, test: list[str], frames: list[str], mount_height: float) -> None:
    """Write the road planes of the data set's ``frames`` (the LiDAR ``mount_height`` above the road)
    and the ``testing/`` and ``test_as_val/`` views of ``root`` for its test frames ``test``. They are
    derived from ImageSets/test.txt and the calib files, so meta/dataset.json does not list them."""
    root = Path(root)
    write_planes(root, frames, mount_height)
    for kind in TESTING_KINDS:
        _sync_links(root / "testing" / kind, _frame_links(test, kind, 2))
    view = root / VIEW_ROOT
    for kind in kitti.KINDS:
        _sync_links(view / "training" / kind, _frame_links(test, kind, 3))
    _sync_links(view / "training" / PLANES, {f"{i}.txt": str(Path("..", "..", "..", "training", PLANES, f"{i}.txt"))
                                               for i in test})
    for split, ids in (("train", []), ("val", test), ("test", [])):
        if test:
            kitti.write_image_set(view / "ImageSets" / f"{split}.txt", ids)
        else:  # no test frames (training scenes): no view
            (view / "ImageSets" / f"{split}.txt").unlink(missing_ok=True)
