"""The settled hit: which triangle a ray meets first, the same on every CPU.

Embree's answer for a ray that passes within rounding of a triangle's edge depends on the CPU (its kernels
and each vendor's reciprocal estimates). A ray's hit is defined here as the nearest triangle it meets in
float64 (Moller-Trumbore on the float32 triangles and ray, edges included; ties: the lower index), and
Embree only proposes a candidate: it casts against the triangles grown by ``GROW_M`` in their planes, so a
triangle the ray meets is one Embree meets by a margin far above its rounding, on every CPU, and no
triangle met lies in front of the candidate's plane by more than Embree's rounding along the ray
(``settle``; large only where the ray grazes a triangle). A ray that meets its candidate is settled among
it and the triangles near the meeting point (a grid of ``CELL_M`` cells); a ray that grazes the candidate
or passes beside it (within GROW_M of an edge) walks the grid from before it and tests every triangle it
crosses. Every decision is float64 arithmetic without fused multiply-adds, the same on every x86-64 CPU.
``Mesh`` holds a triangle soup as the ray caster (simulator.raycast) settles hits on it.
"""
from __future__ import annotations

import numba
import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

GROW_M = 1e-3  # metres each triangle grows by for Embree's cast: 10x Embree's rounding over 120 m of float32
MAX_MOVE_M = 1.0  # and each corner by at most this (the world's and the vehicles' triangles: < 0.5 m)
CELL_M = 2.0  # the grid of triangles a hit is settled among
# how far Embree's meeting with a grown triangle's plane may lie off the triangle's float64 plane, in float32 ulps
# of the magnitude (_planes, _drift; measured: 0.8 at most, 0.3 where the ray meets the plane at |cos| < 0.05)
DRIFT_ULPS = 2.0
F32_ULP = 2.0 ** -23  # float32's ulp relative to the magnitude (at most)
FOLD_DEG = 30.0  # neighbours that fold back over each other to within this angle crowd each other (settle)


def embree_scene(triangles: np.ndarray) -> rtcs.EmbreeScene:
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(triangles, dtype=np.float32))
    return scene


def embree_cast(scene: rtcs.EmbreeScene, origins: np.ndarray, dirs: np.ndarray, max_t: float | np.ndarray = 1e37) -> dict:
    """First hits up to max_t (a number, or per ray: a float32 array that Embree overwrites)."""
    return scene.run(np.ascontiguousarray(origins, dtype=np.float32),
                     np.ascontiguousarray(dirs, dtype=np.float32), dists=max_t, output=1)


def grown(triangles: np.ndarray, by: float = GROW_M, most: float = MAX_MOVE_M) -> np.ndarray:
    """(T, 3, 3) float32 triangles scaled about their centroids so that every edge moves out by at least
    2 ``by`` metres in the triangle's plane (twice: float32's rounding of the grown corners), no corner by
    more than ``most`` (a sliver is grown less; degenerate triangles unchanged)."""
    tris = np.asarray(triangles, dtype=np.float64)
    c = tris.mean(1, keepdims=True)
    area2 = np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)  # 2 x area
    edges = np.linalg.norm(tris[:, [1, 2, 0]] - tris, axis=2).max(1)
    inset = area2 / (3.0 * np.maximum(edges, 1e-30))  # the centroid's distance to its nearest edge line
    reach = np.linalg.norm(tris - c, axis=2).max(1)  # the centroid's distance to its farthest corner
    scale = np.minimum(1.0 + 2.0 * by / np.maximum(inset, 1e-30), 1.0 + most / np.maximum(reach, 1e-30))
    return (c + (tris - c) * np.where(area2 > 0, scale, 1.0)[:, None, None]).astype(np.float32)


@numba.njit(cache=True)
def _grid(tris, cell, pad):
    """Triangles by the (x, y) cells of ``cell`` metres their bounding boxes, grown by ``pad``, overlap:
    (x0, y0, nx, ny, cell), CSR starts (nx * ny + 1,) and triangle indices (ascending within a cell)."""
    n = tris.shape[0]
    lo = np.empty((n, 2))
    hi = np.empty((n, 2))
    for k in range(n):
        for a in range(2):
            lo[k, a] = min(tris[k, 0, a], tris[k, 1, a], tris[k, 2, a]) - pad
            hi[k, a] = max(tris[k, 0, a], tris[k, 1, a], tris[k, 2, a]) + pad
    x0, y0 = lo[:, 0].min(), lo[:, 1].min()
    nx = int((hi[:, 0].max() - x0) // cell) + 1
    ny = int((hi[:, 1].max() - y0) // cell) + 1
    counts = np.zeros(nx * ny + 1, np.int64)
    for k in range(n):
        for ix in range(int((lo[k, 0] - x0) // cell), int((hi[k, 0] - x0) // cell) + 1):
            for iy in range(int((lo[k, 1] - y0) // cell), int((hi[k, 1] - y0) // cell) + 1):
                counts[ix * ny + iy + 1] += 1
    starts = np.cumsum(counts)
    fill = starts[:-1].copy()
    items = np.empty(starts[-1], np.int64)
    for k in range(n):
        for ix in range(int((lo[k, 0] - x0) // cell), int((hi[k, 0] - x0) // cell) + 1):
            for iy in range(int((lo[k, 1] - y0) // cell), int((hi[k, 1] - y0) // cell) + 1):
                items[fill[ix * ny + iy]] = k
                fill[ix * ny + iy] += 1
    return np.array([x0, y0, nx, ny, cell]), starts, items


@numba.njit(cache=True)
def _crowding(tris, bounds, box, starts, items, pad):
    """(T, 2, 3) float64 boxes, each triangle's crowding region: the bounding box, over the triangles q that
    share no corner with p and come within ``pad`` of it (bounds that overlap, and neither lies to one side
    of the other's plane or outside one of its edges by more than pad: q may cross p or touch it, so that a
    ray may meet both at one distance), of p's bounds intersected with q's (``bounds``: grown by pad, as the
    grid's). Empty (lo = inf, hi = -inf) when none comes near. Each pair is tested once, in the first grid
    cell that lists both: the triangles' cells are rectangles, so that is (max of the first columns, max of
    the first rows)."""
    ny = int(box[3])
    first = np.full(tris.shape[0], -1, np.int64)  # (T,) each triangle's first cell
    for c in range(starts.shape[0] - 1):
        for j in range(starts[c], starts[c + 1]):
            if first[items[j]] < 0:
                first[items[j]] = c
    col, row = first // ny, first % ny
    region = np.empty_like(bounds)
    region[:, 0] = np.inf
    region[:, 1] = -np.inf
    lo, hi = np.empty(3), np.empty(3)
    for c in range(starts.shape[0] - 1):
        for j in range(starts[c], starts[c + 1]):
            a = items[j]
            for k in range(j + 1, starts[c + 1]):
                b = items[k]
                if max(col[a], col[b]) * ny + max(row[a], row[b]) != c:
                    continue  # tested in an earlier cell
                for x in range(3):
                    lo[x], hi[x] = max(bounds[a, 0, x], bounds[b, 0, x]), min(bounds[a, 1, x], bounds[b, 1, x])
                if lo[0] > hi[0] or lo[1] > hi[1] or lo[2] > hi[2]:
                    continue
                if not _neighbours(tris, a, b) and not _apart(tris, a, b, pad) and not _apart(tris, b, a, pad):
                    for x in range(3):
                        region[a, 0, x], region[a, 1, x] = min(region[a, 0, x], lo[x]), max(region[a, 1, x], hi[x])
                        region[b, 0, x], region[b, 1, x] = min(region[b, 0, x], lo[x]), max(region[b, 1, x], hi[x])
    return region


@numba.njit(cache=True)
def _neighbours(tris, a, b):
    """Triangles a and b share one corner, or two and open at that edge by more than ``FOLD_DEG`` (the angle
    between their half-planes; less, they fold back over each other, as the two sides of a double-sided face)."""
    mine, theirs, n = np.zeros(3, np.bool_), np.zeros(3, np.bool_), 0
    for u in range(3):
        for v in range(3):
            if tris[a, u, 0] == tris[b, v, 0] and tris[a, u, 1] == tris[b, v, 1] and tris[a, u, 2] == tris[b, v, 2]:
                mine[u], theirs[v], n = True, True, n + 1
    if n != 2:
        return n == 1
    s = 0 if mine[0] else 1  # a shared corner, the other one e, and each triangle's own corner
    e = 2 if mine[2] else 1
    own_a, own_b = np.argmin(mine), np.argmin(theirs)
    lx, ly, lz = (np.float64(tris[a, e, 0]) - np.float64(tris[a, s, 0]), np.float64(tris[a, e, 1])
                  - np.float64(tris[a, s, 1]), np.float64(tris[a, e, 2]) - np.float64(tris[a, s, 2]))
    ll = lx * lx + ly * ly + lz * lz
    across = np.zeros((2, 3))  # each own corner's offset from the edge's line
    for r, (k, c) in enumerate(((a, own_a), (b, own_b))):
        px, py, pz = (np.float64(tris[k, c, 0]) - np.float64(tris[a, s, 0]), np.float64(tris[k, c, 1])
                      - np.float64(tris[a, s, 1]), np.float64(tris[k, c, 2]) - np.float64(tris[a, s, 2]))
        f = (px * lx + py * ly + pz * lz) / ll
        across[r, 0], across[r, 1], across[r, 2] = px - f * lx, py - f * ly, pz - f * lz
    dot = across[0, 0] * across[1, 0] + across[0, 1] * across[1, 1] + across[0, 2] * across[1, 2]
    lengths = np.sqrt((across[0] ** 2).sum() * (across[1] ** 2).sum())
    return dot <= np.cos(np.radians(FOLD_DEG)) * lengths


@numba.njit(cache=True)
def _normal(tris, k):
    """Triangle k's normal (v1 - v0) x (v2 - v0) in float64, not normalised."""
    ax, ay, az = np.float64(tris[k, 0, 0]), np.float64(tris[k, 0, 1]), np.float64(tris[k, 0, 2])
    e1x, e1y, e1z = np.float64(tris[k, 1, 0]) - ax, np.float64(tris[k, 1, 1]) - ay, np.float64(tris[k, 1, 2]) - az
    e2x, e2y, e2z = np.float64(tris[k, 2, 0]) - ax, np.float64(tris[k, 2, 1]) - ay, np.float64(tris[k, 2, 2]) - az
    return e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x


@numba.njit(cache=True)
def _apart(tris, a, b, pad):
    """Triangle b lies more than ``pad`` to one side of triangle a's plane or outside one of a's edges."""
    ax, ay, az = np.float64(tris[a, 0, 0]), np.float64(tris[a, 0, 1]), np.float64(tris[a, 0, 2])
    nx, ny, nz = _normal(tris, a)
    nn = np.sqrt(nx * nx + ny * ny + nz * nz)
    if nn == 0.0:
        return False
    nx, ny, nz = nx / nn, ny / nn, nz / nn
    lo, hi = np.inf, -np.inf
    for v in range(3):
        dist = ((np.float64(tris[b, v, 0]) - ax) * nx + (np.float64(tris[b, v, 1]) - ay) * ny
                + (np.float64(tris[b, v, 2]) - az) * nz)
        lo, hi = min(lo, dist), max(hi, dist)
    if lo > pad or hi < -pad:
        return True
    for e in range(3):  # outward normal of edge e in a's plane: edge x n (a is counter-clockwise about n)
        sx, sy, sz = np.float64(tris[a, e, 0]), np.float64(tris[a, e, 1]), np.float64(tris[a, e, 2])
        f = (e + 1) % 3
        ex, ey, ez = np.float64(tris[a, f, 0]) - sx, np.float64(tris[a, f, 1]) - sy, np.float64(tris[a, f, 2]) - sz
        mx, my, mz = ey * nz - ez * ny, ez * nx - ex * nz, ex * ny - ey * nx
        mm = np.sqrt(mx * mx + my * my + mz * mz)
        if mm == 0.0:
            continue
        outside = np.inf
        for v in range(3):
            outside = min(outside, ((np.float64(tris[b, v, 0]) - sx) * mx + (np.float64(tris[b, v, 1]) - sy) * my
                                    + (np.float64(tris[b, v, 2]) - sz) * mz) / mm)
        if outside > pad:
            return True
    return False


@numba.njit(cache=True)
def _planes(tris, big):
    """(T, 4) float64: each triangle's unit normal and how far off its plane Embree's float32 plane of its grown
    copy (``big``, float32) may lie per float32 ulp of magnitude (metres): the grown corners' largest coordinate
    (their rounding, and Embree's differences from the ray's origin) plus the length over which the rounding of
    Embree's float32 normal (e1 x e2, e = v - v0: each component off by an ulp of |e1_y e2_z| + |e1_z e2_y|,
    ...) tilts the plane about v0 (long for slivers). Degenerate triangles: a zero normal, an infinite length."""
    out = np.zeros((tris.shape[0], 4))
    for k in range(tris.shape[0]):
        nx, ny, nz = _normal(tris, k)
        nn = np.sqrt(nx * nx + ny * ny + nz * nz)
        gx, gy, gz = _normal(big, k)
        gn = np.sqrt(gx * gx + gy * gy + gz * gz)
        if nn == 0.0 or gn == 0.0:
            out[k, 3] = np.inf
            continue
        mag = 0.0
        e1, e2 = np.empty(3), np.empty(3)
        for a in range(3):
            mag = max(mag, abs(np.float64(big[k, 0, a])), abs(np.float64(big[k, 1, a])), abs(np.float64(big[k, 2, a])))
            e1[a] = abs(np.float64(big[k, 1, a]) - np.float64(big[k, 0, a]))
            e2[a] = abs(np.float64(big[k, 2, a]) - np.float64(big[k, 0, a]))
        tilt = 0.0  # |rounding of the normal's components| / ulp: |a_y b_z| + |a_z b_y|, ...
        for a in range(3):
            b, c = (a + 1) % 3, (a + 2) % 3
            tilt += (e1[b] * e2[c] + e1[c] * e2[b]) ** 2
        longest = np.sqrt(max(e1[0] ** 2 + e1[1] ** 2 + e1[2] ** 2, e2[0] ** 2 + e2[1] ** 2 + e2[2] ** 2))
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = nx / nn, ny / nn, nz / nn, mag + np.sqrt(tilt) * longest / gn
    return out


@numba.njit(cache=True)
def _drift(planes, k, d, t):
    """How far along the ray o + t d (t: where it meets triangle k's plane, nan: parallel) Embree's meeting with
    k's grown copy may lie from t: DRIFT_ULPS float32 ulps of the magnitude (``_planes``' length for k plus t)
    over |cos| between the ray and k's normal (inf: the ray runs in the plane)."""
    dx, dy, dz = np.float64(d[0]), np.float64(d[1]), np.float64(d[2])
    along = abs(dx * planes[k, 0] + dy * planes[k, 1] + dz * planes[k, 2])
    if not along > 0.0 or t != t:
        return np.inf
    return DRIFT_ULPS * F32_ULP * (planes[k, 3] + abs(t)) * np.sqrt(dx * dx + dy * dy + dz * dz) / along


class Mesh:
    """A triangle soup as the ray caster settles hits on it: the triangles, Embree's scene of them grown
    by GROW_M, the triangles near each (x, y) cell of CELL_M metres and each triangle's crowding region."""

    def __init__(self, triangles: np.ndarray):
        self.triangles = np.ascontiguousarray(triangles, dtype=np.float32)
        big = grown(self.triangles, GROW_M)
        self.embree = embree_scene(big)
        self.planes = _planes(self.triangles, big)  # (T, 4) unit normals and lengths for Embree's rounding
        self.pad = 4.0 * GROW_M  # how near the point where the ray meets a candidate's plane others are sought
        self.grid = _grid(self.triangles, CELL_M, self.pad)
        t64 = self.triangles.astype(np.float64)
        self.bounds = np.stack([t64.min(1) - self.pad, t64.max(1) + self.pad], 1)  # (T, 2, 3)
        self.region = _crowding(self.triangles, self.bounds, *self.grid, self.pad)  # (T, 2, 3)

    def first_hits(self, origins32: np.ndarray, dirs32: np.ndarray, max_t: float | np.ndarray = 1e37) -> dict:
        """Settled first hits up to max_t (a number or per ray): primID (N,) (-1: none), tfar (N,) float32
        and Ng (N, 3) float32 recomputed from the triangle (exact_hits; tfar stays max_t on a miss)."""
        n = len(dirs32)
        limit = np.broadcast_to(np.asarray(max_t, np.float64), (n,)).copy()
        # Embree's limit beyond the exact one by more than a settled drift (pad / 2): the limit itself is applied
        # in float64 (settle)
        res = embree_cast(self.embree, origins32, dirs32,
                   (np.minimum(limit, 1e37) * (1 + 1e-5) + self.pad).astype(np.float32))
        prim = settle(self.triangles, self.planes, self.bounds, self.region, *self.grid, self.pad,
                      res["primID"].astype(np.int64), origins32, dirs32, limit)
        tfar = np.where(prim >= 0, 0.0, np.minimum(limit, 1e37)).astype(np.float32)
        tfar, ng = exact_hits(self.triangles, prim, origins32, dirs32, tfar)
        return {"primID": prim, "tfar": tfar, "Ng": ng}


@numba.njit(cache=True)
def _meet(tris, k, o, d):
    """The ray o + t d against triangle k in float64 (Moller-Trumbore): t, or nan when the ray misses the
    triangle (a point on an edge meets it) or runs parallel to its plane; and t of the plane (nan: parallel)."""
    ax, ay, az = np.float64(tris[k, 0, 0]), np.float64(tris[k, 0, 1]), np.float64(tris[k, 0, 2])
    e1x, e1y, e1z = np.float64(tris[k, 1, 0]) - ax, np.float64(tris[k, 1, 1]) - ay, np.float64(tris[k, 1, 2]) - az
    e2x, e2y, e2z = np.float64(tris[k, 2, 0]) - ax, np.float64(tris[k, 2, 1]) - ay, np.float64(tris[k, 2, 2]) - az
    dx, dy, dz = np.float64(d[0]), np.float64(d[1]), np.float64(d[2])
    px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if det == 0.0:
        return np.nan, np.nan
    inv = 1.0 / det
    sx, sy, sz = np.float64(o[0]) - ax, np.float64(o[1]) - ay, np.float64(o[2]) - az
    u = (sx * px + sy * py + sz * pz) * inv
    qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    t = (e2x * qx + e2y * qy + e2z * qz) * inv
    if u < 0.0 or v < 0.0 or u + v > 1.0:
        return np.nan, t
    return t, t


@numba.njit(cache=True)
def _inside(tris, k, hx, hy, hz):
    """How far the point (hx, hy, hz), on triangle k's plane, lies inside its nearest edge (metres;
    negative outside): the least over the edges of (edge x (point - edge start)) . n / |edge| / |n|."""
    nx_, ny_, nz_ = _normal(tris, k)
    nn = np.sqrt(nx_ * nx_ + ny_ * ny_ + nz_ * nz_)
    if nn == 0.0:
        return -np.inf
    least = np.inf
    for e in range(3):
        sx, sy, sz = np.float64(tris[k, e, 0]), np.float64(tris[k, e, 1]), np.float64(tris[k, e, 2])
        f = (e + 1) % 3
        ex, ey, ez = np.float64(tris[k, f, 0]) - sx, np.float64(tris[k, f, 1]) - sy, np.float64(tris[k, f, 2]) - sz
        px, py, pz = hx - sx, hy - sy, hz - sz
        cx, cy, cz = ey * pz - ez * py, ez * px - ex * pz, ex * py - ey * px
        length = np.sqrt(ex * ex + ey * ey + ez * ez)
        if length == 0.0:
            return -np.inf
        least = min(least, (cx * nx_ + cy * ny_ + cz * nz_) / (length * nn))
    return least


@numba.njit(cache=True)
def _outside(boxes, k, x, y, z):
    """The point (x, y, z) lies outside box k of ``boxes`` (T, 2, 3) (always, when the box is empty)."""
    return (x < boxes[k, 0, 0] or x > boxes[k, 1, 0] or y < boxes[k, 0, 1] or y > boxes[k, 1, 1]
            or z < boxes[k, 0, 2] or z > boxes[k, 1, 2])


@numba.njit(cache=True)
def _cell_nearest(tris, bounds, starts, items, c, o, d, near, hx, hy, hz, limit, best, best_t):
    """The nearest of ``best`` (at best_t) and the triangles of grid cell c that the ray meets at
    0 < t <= limit (ties: the lower index); when ``near``, only triangles whose bounds hold (hx, hy, hz)."""
    for j in range(starts[c], starts[c + 1]):
        q = items[j]
        if near and (hx < bounds[q, 0, 0] or hx > bounds[q, 1, 0] or hy < bounds[q, 0, 1]
                     or hy > bounds[q, 1, 1] or hz < bounds[q, 0, 2] or hz > bounds[q, 1, 2]):
            continue
        tq = _meet(tris, q, o, d)[0]
        if tq > 0.0 and tq <= limit and (tq < best_t or (tq == best_t and q < best)):
            best, best_t = q, tq
    return best, best_t


@numba.njit(cache=True)
def _walk(tris, bounds, box, starts, items, o, d, t0, limit):
    """The nearest triangle the ray meets at 0 < t <= limit (-1: none), walking the grid cells the ray
    crosses from t0 on (Amanatides & Woo's traversal in x, y) and testing every triangle in them."""
    x0, y0, nx, ny, cell = box[0], box[1], int(box[2]), int(box[3]), box[4]
    ox, oy, dx, dy = np.float64(o[0]), np.float64(o[1]), np.float64(d[0]), np.float64(d[1])
    lo, hi = t0, min(limit, 1e30)
    for a0, n_a, oa, da in ((x0, nx, ox, dx), (y0, ny, oy, dy)):  # clip to the grid's box
        if da != 0.0:
            ta, tb = (a0 - oa) / da, (a0 + n_a * cell - oa) / da
            lo, hi = max(lo, min(ta, tb)), min(hi, max(ta, tb))
        elif oa < a0 or oa > a0 + n_a * cell:
            return -1
    if lo > hi:
        return -1
    ix = min(max(int((ox + lo * dx - x0) // cell), 0), nx - 1)
    iy = min(max(int((oy + lo * dy - y0) // cell), 0), ny - 1)
    sx, sy = (1 if dx > 0 else -1), (1 if dy > 0 else -1)
    next_x = (x0 + (ix + (1 if dx > 0 else 0)) * cell - ox) / dx if dx != 0.0 else np.inf
    next_y = (y0 + (iy + (1 if dy > 0 else 0)) * cell - oy) / dy if dy != 0.0 else np.inf
    step_x = cell / abs(dx) if dx != 0.0 else np.inf
    step_y = cell / abs(dy) if dy != 0.0 else np.inf
    best, best_t = -1, np.inf
    while True:
        best, best_t = _cell_nearest(tris, bounds, starts, items, ix * ny + iy, o, d, False, 0.0, 0.0, 0.0, limit,
                                     best, best_t)
        t_exit = min(next_x, next_y)
        if best_t <= t_exit or t_exit > hi:  # a triangle met in this cell lies in it or in one walked
            return best
        if next_x < next_y:
            ix, next_x = ix + sx, next_x + step_x
        else:
            iy, next_y = iy + sy, next_y + step_y
        if not (0 <= ix < nx and 0 <= iy < ny):
            return best


@numba.njit(cache=True)
def settle(tris, planes, bounds, region, box, starts, items, pad, prim, origins, dirs, limit):
    """Each ray's triangle (N,) (-1: none): the nearest the ray meets in float64 at 0 < t <= limit (ties: the
    lower index), found from Embree's candidate ``prim`` on the grown triangles (-1: none, so none met).

    Embree's float32 meeting with a grown triangle k lies within drift_k of the ray's float64 meeting with k's
    plane (``_drift``: DRIFT_ULPS float32 ulps of the magnitude over |cos| between ray and normal; 1e-4 m
    head-on 300 m out, 0.1 m at |cos| 1e-3), and its error across the triangle is as large. So Embree meets
    every triangle met with a drift below the 2 mm it is grown by, and returns p although q is met in front
    of it only when q is met within drift_p + drift_q before p's plane. With both at most pad / 2:

    - the ray meets p at h (drift_p <= pad / 2): q is met within pad of h, so its bounds (T, 2, 3, grown by
      ``pad``) hold h, and the triangles of h's grid cell (``_grid``) whose bounds hold h are tested too,
      unless h lies r >= max(pad / 2, 4 drift_p) inside p and outside p's crowding region (``_crowding``).
      That skip is exact: outside the region h lies outside the bounds of every triangle that comes within
      pad of p but p's neighbours (the region's corners are the bounds' own numbers), and one that does not
      is met more than pad from h. A neighbour across an edge at an angle a to p meets the ray r sin(a) /
      |cos_q| before h: more than drift_p + drift_q for a from 30 to 150 degrees (r sin(a) >= 2 drift_p and
      >= 1 mm, far above float32's rounding across q's plane); a flatter one lies r from h, so the ray would
      have to graze it 3 times more than p, which a plane within 30 degrees of p's allows only where q's
      rounding is over twice p's (a sliver beside a large triangle); a sharper one makes the pair crowd each
      other (``_neighbours``: the two sides of a double-sided sign); one sharing a corner would have to
      reach over p's inside;
    - the ray grazes p (drift_p > pad / 2) or passes beside it: the grid is walked (``_walk``) from
      pad + drift_p before p's plane.

    Not covered: a ray that meets its nearest triangle with a drift over pad / 2 (|cos| below 0.036 where
    the magnitude and the distance add up to 300 m; 0.005 for the rounding measured), which Embree may miss
    near an open edge or order behind a steeper triangle."""
    n = prim.shape[0]
    out = np.full(n, -1, np.int32)
    x0, y0, nx, ny, cell = box[0], box[1], int(box[2]), int(box[3]), box[4]
    for i in range(n):
        p = prim[i]
        if p < 0:
            continue  # nothing within GROW_M of the ray: a miss
        met, t = _meet(tris, p, origins[i], dirs[i])
        drift = _drift(planes, p, dirs[i], t)
        if met > 0.0 and met <= limit[i] and drift <= 0.5 * pad:
            hx = np.float64(origins[i, 0]) + met * np.float64(dirs[i, 0])
            hy = np.float64(origins[i, 1]) + met * np.float64(dirs[i, 1])
            hz = np.float64(origins[i, 2]) + met * np.float64(dirs[i, 2])
            out[i] = p
            if _outside(region, p, hx, hy, hz) and _inside(tris, p, hx, hy, hz) >= max(0.5 * pad, 4.0 * drift):
                continue
            ix, iy = int((hx - x0) // cell), int((hy - y0) // cell)
            if 0 <= ix < nx and 0 <= iy < ny:
                out[i] = _cell_nearest(tris, bounds, starts, items, ix * ny + iy, origins[i], dirs[i], True, hx, hy, hz,
                                       limit[i], p, met)[0]
        elif not (t - drift > limit[i] + pad):  # (t nan: the ray runs in p's plane)
            out[i] = _walk(tris, bounds, box, starts, items, origins[i], dirs[i],
                           max(t - pad - drift, 0.0) if t == t else 0.0, limit[i])
    return out


@numba.njit(cache=True)
def exact_hits(tris: np.ndarray, prim: np.ndarray, origins: np.ndarray, dirs: np.ndarray,
               tfar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (N,) float32 and geometric normal (N, 3) float32 of each ray's hit triangle prim (N,),
    computed in float64 from the float32 triangles (T, 3, 3) and rays (N, 3): the ray meets the
    triangle's plane at t = ((v0 - o) . n) / (d . n), n = (v1 - v0) x (v2 - v0). Misses (prim < 0)
    keep tfar. Plain IEEE products and sums (no fused multiply-add, no library call), so the result
    does not depend on the instruction set."""
    n = prim.shape[0]
    t_out = tfar.astype(np.float32)
    ng = np.zeros((n, 3), np.float32)
    for i in range(n):
        p = prim[i]
        if p < 0:
            continue
        ax, ay, az = np.float64(tris[p, 0, 0]), np.float64(tris[p, 0, 1]), np.float64(tris[p, 0, 2])
        nx, ny, nz = _normal(tris, p)
        denom = np.float64(dirs[i, 0]) * nx + np.float64(dirs[i, 1]) * ny + np.float64(dirs[i, 2]) * nz
        if denom != 0.0:
            ox, oy, oz = np.float64(origins[i, 0]), np.float64(origins[i, 1]), np.float64(origins[i, 2])
            t_out[i] = ((ax - ox) * nx + (ay - oy) * ny + (az - oz) * nz) / denom
        ng[i, 0], ng[i, 1], ng[i, 2] = nx, ny, nz
    return t_out, ng
