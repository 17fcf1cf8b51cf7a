"""Procedural vehicles: six body types built from extruded side profiles, glass, lights, wheels.

Templates live in a unit frame (x forward in [-0.5, 0.5], y left in [-0.5, 0.5], z up in
[0, 1]) and are scaled by the vehicle's (l, w, h), so the labelled box is exactly the mesh's
bounding box. Wheels are added in metres so that they stay round.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from shapely.geometry import Polygon

from simulator.materials import ID, PAINT_NAMES, paint_id
from simulator.prims import UNIT_BOX, UNIT_PRISM, place, rot_z

PAINT = 255  # template placeholder for the vehicle's paint


@dataclass(frozen=True)
class BodyType:
    label: str  # KITTI class
    dims: tuple[float, float, float]  # mean (l, w, h), metres
    body: tuple  # side profile (x, z) of the painted lower body, unit frame
    cabin: tuple  # side profile of the greenhouse
    cabin_width: float  # share of the width
    glass_from_x: float  # cabin side faces behind this x stay painted (vans)
    wheel_radius: float  # m
    axles: tuple[float, ...]  # axle x positions as shares of the length


BODY_TYPES: dict[str, BodyType] = {
    "sedan": BodyType("Car", (4.75, 1.83, 1.45),
                      ((-.5, .18), (.5, .18), (.5, .42), (.46, .52), (.18, .58), (-.4, .62), (-.5, .58)),
                      ((-.37, .6), (.17, .57), (.0, 1.), (-.27, 1.)), 0.86, -1.0, 0.32, (-.31, .3)),
    "coupe": BodyType("Car", (4.55, 1.82, 1.32),
                      ((-.5, .18), (.5, .18), (.5, .4), (.45, .5), (.15, .58), (-.45, .62), (-.5, .56)),
                      ((-.4, .6), (.13, .57), (-.06, 1.), (-.23, 1.)), 0.84, -1.0, 0.32, (-.31, .31)),
    "hatchback": BodyType("Car", (4.15, 1.78, 1.50),
                          ((-.5, .18), (.5, .18), (.5, .44), (.42, .55), (.2, .6), (-.5, .62)),
                          ((-.49, .6), (.2, .58), (.02, 1.), (-.46, 1.)), 0.86, -1.0, 0.31, (-.32, .31)),
    "suv": BodyType("Car", (4.70, 1.90, 1.72),
                    ((-.5, .2), (.5, .2), (.5, .48), (.43, .58), (.25, .62), (-.5, .63)),
                    ((-.49, .61), (.25, .6), (.1, 1.), (-.48, 1.)), 0.9, -1.0, 0.36, (-.3, .3)),
    "van": BodyType("Van", (5.20, 2.00, 2.15),
                    ((-.5, .12), (.5, .12), (.5, .45), (.41, .6), (-.5, .6)),
                    ((-.5, .59), (.41, .59), (.3, 1.), (-.5, 1.)), 0.98, 0.12, 0.34, (-.32, .3)),
    "truck": BodyType("Truck", (11.5, 2.55, 3.80),
                      ((.33, .1), (.5, .1), (.5, .45), (.47, .85), (.33, .85)),
                      ((-.5, .2), (.31, .2), (.31, 1.), (-.5, 1.)), 1.0, 2.0, 0.5, (-.4, -.3, .38)),
}
BODY_NAMES = tuple(BODY_TYPES)


def _extrude(profile: tuple, width: float) -> np.ndarray:
    """Triangles of a star-shaped side profile (x, z) extruded across y in [-width/2, width/2]."""
    p = np.asarray(Polygon(profile).exterior.coords)[:-1]  # (P, 2)
    c = Polygon(profile).centroid.coords[0]
    q = np.roll(p, -1, axis=0)
    tris = []
    for y in (-width / 2, width / 2):
        def v3(a: np.ndarray) -> np.ndarray:
            return np.stack([a[:, 0], np.full(len(a), y), a[:, 1]], 1)
        cen = np.tile([[c[0], y, c[1]]], (len(p), 1))
        tris.append(np.stack([cen, v3(p), v3(q)], 1))  # cap fan
    lo, hi = -width / 2, width / 2
    a = np.stack([p[:, 0], np.full(len(p), lo), p[:, 1]], 1)
    b = np.stack([q[:, 0], np.full(len(p), lo), q[:, 1]], 1)
    a2, b2 = a.copy(), b.copy()
    a2[:, 1] = hi
    b2[:, 1] = hi
    tris += [np.stack([a, b, b2], 1), np.stack([a, b2, a2], 1)]
    return np.concatenate(tris)


def _normals(tris: np.ndarray) -> np.ndarray:
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


@lru_cache(maxsize=None)
def body_template(name: str) -> tuple[np.ndarray, np.ndarray]:
    """Unit-frame triangles (T, 3, 3) and material codes (T,) (PAINT = vehicle paint)."""
    bt = BODY_TYPES[name]
    body = _extrude(bt.body, 0.98)
    cabin = _extrude(bt.cabin, bt.cabin_width)
    n = _normals(cabin)
    cx = cabin.mean(1)[:, 0]
    glass = (np.abs(n[:, 2]) < 0.7) & (cx > bt.glass_from_x)
    if name == "truck":  # windscreen on the cab, box trailer painted
        bn, bx = _normals(body), body.mean(1)
        cab_glass = (bn[:, 0] > 0.5) & (bx[:, 2] > 0.5)
    else:
        cab_glass = np.zeros(len(body), bool)
    lights = []
    for y in (-0.33, 0.33):
        lights.append((place(UNIT_BOX, np.array([[0.4925, y, 0.4 if name != "truck" else 0.2]]),
                             np.array([0.015, 0.18, 0.06]), 0.0), ID["headlight"]))
        lights.append((place(UNIT_BOX, np.array([[-0.4925, y, 0.5 if name != "truck" else 0.25]]),
                             np.array([0.015, 0.14, 0.05]), 0.0), ID["taillight"]))
    tris = [body, cabin] + [t for t, _ in lights]
    mats = [np.where(cab_glass, ID["glass"], PAINT), np.where(glass, ID["glass"], PAINT)]
    mats += [np.full(len(t), m) for t, m in lights]
    return np.concatenate(tris), np.concatenate(mats).astype(np.int64)


WHEEL = UNIT_PRISM[:, :, [0, 2, 1]]  # cylinder axis along y


def vehicle_mesh(name: str, dims: np.ndarray, paint: str) -> tuple[np.ndarray, np.ndarray]:
    """Vehicle-frame triangles (box centre at (0, 0, h/2)) and material ids."""
    bt = BODY_TYPES[name]
    l, w, h = dims
    tris, codes = body_template(name)
    tris = tris * np.array([l, w, h]) - np.array([0.0, 0.0, h / 2])
    r, tw = bt.wheel_radius, 0.25 if name != "truck" else 0.4
    centres = np.array([[ax * l, s * (w / 2 - tw / 2), r - h / 2] for ax in bt.axles for s in (-1, 1)])
    wheels = place(WHEEL, centres, np.array([2 * r, tw, 2 * r]), np.zeros(len(centres)))
    mats = np.concatenate([np.where(codes == PAINT, paint_id(paint), codes), np.full(len(wheels), ID["tyre"])])
    return np.concatenate([tris, wheels]), mats


@dataclass(frozen=True)
class Vehicle:
    """A vehicle in the world frame; (x, y, z) is the geometric box centre."""

    body: str
    dims: tuple[float, float, float]  # l, w, h metres
    paint: str
    x: float
    y: float
    heading: float  # rad, CCW from world +x
    speed: float  # m/s
    role: str = "traffic"  # "slow", "fast" or "traffic"
    reflectance: float | None = None  # 905 nm reflectance of the paint for the LiDAR; None: materials' table

    @property
    def label(self) -> str:
        return BODY_TYPES[self.body].label

    @property
    def z(self) -> float:
        return self.dims[2] / 2


@lru_cache(maxsize=256)
def _mesh(body: str, dims: tuple[float, float, float], paint: str) -> tuple[np.ndarray, np.ndarray]:
    """vehicle_mesh of a vehicle seen before (a SOTIF run shows the same vehicles every frame), read-only."""
    tris, mats = vehicle_mesh(body, np.asarray(dims), paint)
    tris.flags.writeable = mats.flags.writeable = False
    return tris, mats


def world_triangles(v: Vehicle) -> tuple[np.ndarray, np.ndarray]:
    """World-frame triangles and (read-only) material ids of one vehicle."""
    tris, mats = _mesh(v.body, tuple(float(d) for d in v.dims), v.paint)
    r = rot_z(np.array(v.heading))
    return tris @ r.T + np.array([v.x, v.y, v.z]), mats


def sample_body(rng: np.random.Generator, truck_share: float = 0.1, van_share: float = 0.1) -> str:
    car = (1.0 - truck_share - van_share) / 4
    p = [car, car, car, car, van_share, truck_share]
    return BODY_NAMES[int(rng.choice(len(BODY_NAMES), p=p))]


def sample_dims(body: str, rng: np.random.Generator) -> tuple[float, float, float]:
    l, w, h = BODY_TYPES[body].dims
    if body == "truck":
        l = rng.uniform(9.0, 13.5)
    k = rng.normal(1.0, 0.035, 3).clip(0.92, 1.08)
    return (float(l * k[0]), float(w * k[1]), float(h * k[2]))


def sample_paint(rng: np.random.Generator) -> str:
    p = np.array([0.22, 0.18, 0.17, 0.12, 0.08, 0.08, 0.05, 0.04, 0.03, 0.03])
    return PAINT_NAMES[int(rng.choice(len(PAINT_NAMES), p=p / p.sum()))]
