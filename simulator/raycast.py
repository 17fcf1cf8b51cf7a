"""Embree ray casting over the static world plus the frame's vehicles.

The static world's BVH is built once per process; the vehicles (a few thousand triangles)
get their own small scene each frame, and a ray's first hit is the nearer of the two.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

from simulator.vehicles import Vehicle, world_triangles
from simulator.world import World

MISS = -1  # actor id of rays that hit nothing
STATIC = -2  # actor id of rays that hit the static world


@dataclass
class Hits:
    """First hits of N rays: t (N,) metres (inf on miss), unit normal facing the ray (N, 3),
    material id (N,) (0 on miss), actor index into the frame's vehicles (N,) or MISS/STATIC."""

    t: np.ndarray
    normal: np.ndarray
    material: np.ndarray
    actor: np.ndarray


def _scene(triangles: np.ndarray) -> rtcs.EmbreeScene:
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(triangles, dtype=np.float32))
    return scene


def _run(scene: rtcs.EmbreeScene, origins: np.ndarray, dirs: np.ndarray) -> dict:
    return scene.run(np.ascontiguousarray(origins, dtype=np.float32),
                     np.ascontiguousarray(dirs, dtype=np.float32), output=1)


def first_hit_distance(triangles: np.ndarray, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(N,) distance to the first hit on a triangle soup (inf on miss); dirs must be unit."""
    res = _run(_scene(triangles), origins, dirs)
    return np.where(res["primID"] >= 0, res["tfar"].astype(np.float64), np.inf)


class RayScene:
    """Static world + per-frame vehicles."""

    def __init__(self, world: World):
        self.world = world
        self._static = _scene(world.triangles)
        self._dynamic: rtcs.EmbreeScene | None = None
        self._dyn_material = np.zeros(0, np.int64)
        self._dyn_actor = np.zeros(0, np.int64)
        self.vehicle_triangles: list[np.ndarray] = []

    def set_vehicles(self, vehicles: list[Vehicle]) -> None:
        """Replace the dynamic scene with these vehicles (actor id = list index)."""
        tris, mats, actors = [], [], []
        for i, v in enumerate(vehicles):
            t, m = world_triangles(v)
            tris.append(t)
            mats.append(m)
            actors.append(np.full(len(t), i))
        self.vehicle_triangles = tris
        if not tris:
            self._dynamic = None
            return
        self._dynamic = _scene(np.concatenate(tris))
        self._dyn_material = np.concatenate(mats)
        self._dyn_actor = np.concatenate(actors)

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> Hits:
        """First hits of rays (origins (N, 3) or (3,), unit dirs (N, 3)), world frame."""
        origins = np.broadcast_to(np.asarray(origins, dtype=np.float32), dirs.shape)
        st = _run(self._static, origins, dirs)
        t = np.where(st["primID"] >= 0, st["tfar"], np.inf).astype(np.float64)
        ng = st["Ng"]
        prim = st["primID"]
        material = np.where(prim >= 0, self.world.material[np.maximum(prim, 0)], 0).astype(np.int64)
        actor = np.where(prim >= 0, STATIC, MISS)
        if self._dynamic is not None:
            dy = _run(self._dynamic, origins, dirs)
            td = np.where(dy["primID"] >= 0, dy["tfar"], np.inf)
            nearer = td < t
            t = np.where(nearer, td, t)
            ng = np.where(nearer[:, None], dy["Ng"], ng)
            p = np.maximum(dy["primID"], 0)
            material = np.where(nearer, self._dyn_material[p], material)
            actor = np.where(nearer, self._dyn_actor[p], actor)
        n = ng / np.maximum(np.linalg.norm(ng, axis=1, keepdims=True), 1e-12)
        flip = np.sum(n * dirs, axis=1) > 0
        n[flip] *= -1
        return Hits(t, n, material, actor)
