"""Embree ray casting over the static world plus the frame's vehicles.

The static world's BVH is built once per process; the vehicles (a few thousand triangles)
get their own small scene each frame, and a ray's first hit is the nearer of the two. Which
triangle a ray hits is settled by simulator.settling, not by Embree, so that a seed gives the
same bytes on every CPU.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from simulator.materials import lidar_tables
from simulator import settling
from simulator.settling import Mesh
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


def first_hit_distance(triangles: np.ndarray, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(N,) distance to the first hit on a triangle soup (inf on miss); dirs must be unit."""
    res = settling.embree_cast(settling.embree_scene(triangles), origins, dirs)
    return np.where(res["primID"] >= 0, res["tfar"].astype(np.float64), np.inf)


def rays_near_spheres(origins: np.ndarray, dirs: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(N,) bool: the ray from origins (3,) or (N, 3) along unit dirs (N, 3) passes within a sphere (K, 3), (K,)."""
    origins = np.asarray(origins, dtype=np.float64)
    return _near_spheres(origins.reshape(-1, 3), np.asarray(dirs, dtype=np.float64), centres, radii)


@numba.njit(cache=True)
def _near_spheres(origins: np.ndarray, dirs: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    n, k = dirs.shape[0], centres.shape[0]
    shared = origins.shape[0] == 1
    out = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        o = 0 if shared else i
        for j in range(k):
            cx = centres[j, 0] - origins[o, 0]
            cy = centres[j, 1] - origins[o, 1]
            cz = centres[j, 2] - origins[o, 2]
            along = cx * dirs[i, 0] + cy * dirs[i, 1] + cz * dirs[i, 2]
            if along < -radii[j]:
                continue
            perp2 = cx * cx + cy * cy + cz * cz - along * along
            if perp2 <= radii[j] * radii[j]:
                out[i] = True
                break
    return out


@numba.njit(cache=True)
def rays_hit_triangles(origin: np.ndarray, dirs: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(N,) bool: the ray from origin (3,) along dirs (N, 3) hits one of a few triangles (T, 3, 3) at t >= 0.

    Brute-force Moller-Trumbore; for a handful of rays against one small mesh this is cheaper
    than building an Embree scene."""
    n, m = dirs.shape[0], tris.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        for k in range(m):
            ax, ay, az = tris[k, 0, 0], tris[k, 0, 1], tris[k, 0, 2]
            e1x, e1y, e1z = tris[k, 1, 0] - ax, tris[k, 1, 1] - ay, tris[k, 1, 2] - az
            e2x, e2y, e2z = tris[k, 2, 0] - ax, tris[k, 2, 1] - ay, tris[k, 2, 2] - az
            px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
            det = e1x * px + e1y * py + e1z * pz
            if det == 0.0:
                continue
            inv = 1.0 / det
            sx, sy, sz = origin[0] - ax, origin[1] - ay, origin[2] - az
            u = (sx * px + sy * py + sz * pz) * inv
            if u < 0.0 or u > 1.0:
                continue
            qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
            v = (dx * qx + dy * qy + dz * qz) * inv
            if v < 0.0 or u + v > 1.0:
                continue
            if (e2x * qx + e2y * qy + e2z * qz) * inv >= 0.0:
                out[i] = True
                break
    return out


@numba.njit(cache=True)
def unit_normals_facing(ng: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals turned against the ray directions (zero where ng is zero)."""
    out = np.zeros((ng.shape[0], 3))
    for i in range(ng.shape[0]):
        x, y, z = np.float64(ng[i, 0]), np.float64(ng[i, 1]), np.float64(ng[i, 2])
        norm = np.sqrt(x * x + y * y + z * z)
        if norm == 0.0:
            continue
        if x * dirs[i, 0] + y * dirs[i, 1] + z * dirs[i, 2] > 0:
            norm = -norm
        out[i, 0], out[i, 1], out[i, 2] = x / norm, y / norm, z / norm
    return out


class RayScene:
    """Static world + per-frame vehicles."""

    def __init__(self, world: World):
        self.world = world
        self._static = Mesh(world.triangles)
        self.static_material = world.material.astype(np.int64)  # (T,) material id per world triangle
        self._dynamic: Mesh | None = None
        self._dynamic_triangles = np.zeros((0, 3, 3), np.float32)  # (V, 3, 3) the vehicles' triangles
        self.dyn_material = np.zeros(1, np.int64)  # (V,) per vehicle triangle (one dummy entry when empty)
        self.dyn_actor = np.zeros(1, np.int64)
        self.spheres = (np.zeros((0, 3)), np.zeros(0))  # vehicle bounding spheres: centres (K, 3), radii (K,)
        self.vehicle_triangles: list[np.ndarray] = []
        self.vehicles: list[Vehicle] = []
        self._lidar_tables()

    def set_vehicles(self, vehicles: list[Vehicle]) -> None:
        """Replace the dynamic scene with these vehicles (actor id = list index)."""
        self.vehicles = list(vehicles)
        tris, mats, actors = [], [], []
        for i, v in enumerate(vehicles):
            t, m = world_triangles(v)
            tris.append(t)
            mats.append(m)
            actors.append(np.full(len(t), i))
        self.vehicle_triangles = tris
        self.spheres = (np.array([t.reshape(-1, 3).mean(0) for t in tris]).reshape(-1, 3),
                        np.array([np.linalg.norm(t.reshape(-1, 3) - t.reshape(-1, 3).mean(0), axis=1).max() + 0.01
                                  for t in tris]))
        if not tris:
            self._dynamic, self._dynamic_triangles = None, np.zeros((0, 3, 3), np.float32)
            self.dyn_material, self.dyn_actor = np.zeros(1, np.int64), np.zeros(1, np.int64)
        else:
            self._dynamic_triangles = np.ascontiguousarray(np.concatenate(tris), dtype=np.float32)
            self._dynamic = Mesh(self._dynamic_triangles)
            self.dyn_material = np.concatenate(mats).astype(np.int64)
            self.dyn_actor = np.concatenate(actors).astype(np.int64)
        self._lidar_tables()

    def _lidar_tables(self) -> None:
        """The LiDAR's vehicle materials and tables (materials.lidar_tables: reflectance overrides)."""
        self.lidar_dyn_material, self.lidar_reflectivity, self.lidar_ground = lidar_tables(
            self.dyn_material, self.dyn_actor, self.vehicles)

    def _candidates(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Rays that may hit a vehicle (bounding spheres)."""
        return rays_near_spheres(origin, dirs, *self.spheres)

    def occluded(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """(N,) bool: the ray (origins (N, 3) or (3,), unit dirs (N, 3)) hits anything. Embree's any-hit
        query on the grown triangles clears the rays that pass everything by GROW_M; the rest are settled
        (Mesh.first_hits)."""
        origin = np.asarray(origins, dtype=np.float64)
        origins32 = np.ascontiguousarray(np.broadcast_to(origin.astype(np.float32), dirs.shape))
        dirs32 = np.ascontiguousarray(dirs, dtype=np.float32)
        out = np.zeros(len(dirs32), bool)
        for mesh, rays in ((self._static, np.arange(len(dirs32))),
                           (self._dynamic, np.flatnonzero(self._candidates(origin, dirs)))):
            rays = rays[~out[rays]]
            if mesh is None or not len(rays):
                continue
            maybe = rays[mesh.embree.run(origins32[rays], dirs32[rays], query="OCCLUDED") >= 0]
            if len(maybe):
                out[maybe] = mesh.first_hits(origins32[maybe], dirs32[maybe])["primID"] >= 0
        return out

    def cast_parts(self, origins32: np.ndarray, dirs32: np.ndarray, near: np.ndarray,
                   max_t: float = 1e37) -> tuple[dict, dict]:
        """Settled first hits (``Mesh.first_hits``: triangle, and distance and normal recomputed from it;
        float32 (N, 3) origins and dirs, hits up to max_t): the static world for all rays and the
        vehicles for the rays `near` (sorted indices) only."""
        st = self._static.first_hits(origins32, dirs32, max_t)
        if self._dynamic is None or len(near) == 0:
            return st, {"tfar": np.zeros(0, np.float32), "primID": np.zeros(0, np.int32),
                        "Ng": np.zeros((0, 3), np.float32)}
        # a vehicle counts only when nearer than the static hit: stop each ray there
        return st, self._dynamic.first_hits(origins32[near], dirs32[near], st["tfar"][near])

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> Hits:
        """First hits of rays (origins (N, 3) or (3,), unit dirs (N, 3)), world frame."""
        origin = np.asarray(origins, dtype=np.float64)
        origins32 = np.ascontiguousarray(np.broadcast_to(origin.astype(np.float32), dirs.shape))
        near = np.zeros(0, np.int64)
        if self._dynamic is not None:
            near = np.flatnonzero(self._candidates(origin, dirs))
        st, dy = self.cast_parts(origins32, np.ascontiguousarray(dirs, dtype=np.float32), near)
        return Hits(*merge_hits(st["tfar"], st["primID"], st["Ng"], self.static_material,
                                near, dy["tfar"], dy["primID"], dy["Ng"], self.dyn_material, self.dyn_actor, dirs))


@numba.njit(cache=True)
def merge_hits(t_s, prim_s, ng_s, mat_s, near, t_d, prim_d, ng_d, mat_d, actor_d, dirs):
    """Nearer of the static hit and the vehicle hit (rays `near` only) per ray.

    Returns t (N,) (inf on miss), unit normals facing the ray (N, 3), material (N,) and actor
    (N,) (vehicle index, STATIC or MISS).
    """
    n = t_s.shape[0]
    t = np.full(n, np.inf)
    ng = np.zeros((n, 3), np.float32)
    material = np.zeros(n, np.int64)
    actor = np.full(n, MISS, np.int64)
    for i in range(n):
        if prim_s[i] >= 0:
            t[i] = t_s[i]
            ng[i] = ng_s[i]
            material[i] = mat_s[prim_s[i]]
            actor[i] = STATIC
    for j in range(near.shape[0]):
        i = near[j]
        if prim_d[j] >= 0 and t_d[j] < t[i]:
            t[i] = t_d[j]
            ng[i] = ng_d[j]
            material[i] = mat_d[prim_d[j]]
            actor[i] = actor_d[prim_d[j]]
    return t, unit_normals_facing(ng, dirs), material, actor
