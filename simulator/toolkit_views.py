"""Views of a data set for OpenPCDet's and MMDetection3D's stock KITTI info generation (docs/kitti_tools.md).

Both toolkits read the split named ``test`` from ``testing/`` and the others from ``training/``,
and only ``train`` and ``val`` get labelled infos. Our labelled test frames live in ``training/``
(ImageSets/test.txt), so the data set gets two views made of relative symlinks to its own files:

- ``testing/{velodyne,image_2,calib}/NNNNNN.*``: the test frames where the stock tools look for
  them (no labels, as KITTI's testing set), so ``create_kitti_infos`` runs on ``<root>``;
- ``test_as_val/``: a KITTI root whose ``val`` split is our test split (``training/`` holds links
  to those frames, labels included; ``train`` and ``test`` are empty), so a stock config pointed at
  ``<root>/test_as_val`` evaluates the labelled test frames as its validation set.

Each link is made under a temp name and renamed into place; links the data set no longer plans
are removed (regular files in the views are never touched). The same data set gives the same links.
"""
from __future__ import annotations

import os
import secrets
from pathlib import Path

from harness import kitti

TESTING_KINDS = ("velodyne", "image_2", "calib")
VIEW_ROOT = "test_as_val"


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


def write_views(root: Path, test: list[str]) -> None:
    """Write the ``testing/`` and ``test_as_val/`` views of ``root`` for its test frames ``test``.
    They are derived from ImageSets/test.txt, so meta/dataset.json does not list them."""
    root = Path(root)
    for kind in TESTING_KINDS:
        _sync_links(root / "testing" / kind, _frame_links(test, kind, 2))
    view = root / VIEW_ROOT
    for kind in kitti.KINDS:
        _sync_links(view / "training" / kind, _frame_links(test, kind, 3))
    for split, ids in (("train", []), ("val", test), ("test", [])):
        if test:
            kitti.write_image_set(view / "ImageSets" / f"{split}.txt", ids)
        else:  # no test frames (training scenes): no view
            (view / "ImageSets" / f"{split}.txt").unlink(missing_ok=True)
