"""Triangle-soup primitives: (T, 3, 3) float arrays in metres, placed by vectorised transforms."""
from __future__ import annotations

import signal
import threading

import numpy as np


def _import_trimesh():
    """trimesh's ``__init__`` wraps its optional imports in ``except BaseException``, so a Ctrl-C
    during the import (half a second at the start of every ``simulate``) would be swallowed. In
    the main thread, SIGINT is only noted during the import and raised again after it."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is None:
        import trimesh
        return trimesh
    noted = []
    previous = signal.signal(signal.SIGINT, lambda *_: noted.append(True))
    try:
        import trimesh
    finally:
        signal.signal(signal.SIGINT, previous)
    if noted:
        signal.raise_signal(signal.SIGINT)  # now under the previous handler
    return trimesh


trimesh = _import_trimesh()


def _soup(mesh: trimesh.Trimesh) -> np.ndarray:
    return np.asarray(mesh.triangles, dtype=np.float64)


UNIT_BOX = _soup(trimesh.creation.box((1.0, 1.0, 1.0)))  # (12, 3, 3), centred at origin
UNIT_PRISM = _soup(trimesh.creation.cylinder(radius=0.5, height=1.0, sections=8))  # axis z, centred
UNIT_CONE = _soup(trimesh.creation.cone(radius=0.5, height=1.0, sections=8))  # base at z=0
UNIT_BLOB = _soup(trimesh.creation.icosphere(subdivisions=1, radius=0.5))  # centred


def rot_z(yaw: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations about +z."""
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def place(template: np.ndarray, centres: np.ndarray, sizes: np.ndarray, yaws: np.ndarray) -> np.ndarray:
    """Copies of a unit template scaled by sizes (B, 3), turned by yaws (B,), moved to centres (B, 3)."""
    centres = np.atleast_2d(centres)
    sizes = np.broadcast_to(sizes, centres.shape)
    yaws = np.broadcast_to(np.asarray(yaws, dtype=np.float64), centres.shape[:1])
    scaled = template[None] * sizes[:, None, None, :]  # (B, T, 3, 3)
    turned = np.einsum("bij,btkj->btki", rot_z(yaws), scaled)
    return (turned + centres[:, None, None, :]).reshape(-1, 3, 3)


def quad_grid(v: np.ndarray) -> np.ndarray:
    """Two triangles per cell of a (S, P, 3) vertex grid -> (2 (S-1)(P-1), 3, 3)."""
    a, b, c, d = v[:-1, :-1], v[1:, :-1], v[1:, 1:], v[:-1, 1:]
    return np.concatenate([np.stack([a, b, c], -2), np.stack([a, c, d], -2)]).reshape(-1, 3, 3)
