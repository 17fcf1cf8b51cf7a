"""Surface materials: LiDAR reflectivity at 905 nm, camera albedo (linear RGB) and emission."""
from __future__ import annotations

import numpy as np

#  id: (name, lidar reflectivity, albedo rgb, emission rgb)
_BASE = [
    ("asphalt", 0.12, (0.20, 0.20, 0.22), (0, 0, 0)),
    ("lane_marking", 0.60, (0.85, 0.85, 0.82), (0, 0, 0)),
    ("concrete", 0.35, (0.55, 0.55, 0.52), (0, 0, 0)),
    ("guardrail", 0.50, (0.62, 0.64, 0.66), (0, 0, 0)),
    ("grass", 0.40, (0.22, 0.34, 0.14), (0, 0, 0)),
    ("metal_pole", 0.45, (0.45, 0.46, 0.47), (0, 0, 0)),
    ("sign_face", 0.90, (0.10, 0.30, 0.65), (0, 0, 0)),
    ("foliage", 0.45, (0.12, 0.28, 0.10), (0, 0, 0)),
    ("wood", 0.30, (0.30, 0.22, 0.14), (0, 0, 0)),
    ("glass", 0.08, (0.06, 0.08, 0.10), (0, 0, 0)),
    ("tyre", 0.04, (0.04, 0.04, 0.04), (0, 0, 0)),
    ("headlight", 0.50, (0.80, 0.80, 0.75), (3.0, 2.9, 2.6)),
    ("taillight", 0.40, (0.50, 0.05, 0.05), (1.6, 0.08, 0.05)),
    ("gravel", 0.20, (0.40, 0.38, 0.34), (0, 0, 0)),
    ("trim", 0.08, (0.08, 0.08, 0.09), (0, 0, 0)),
    ("delineator", 0.90, (0.90, 0.90, 0.90), (0, 0, 0)),
]
PAINTS = {  # name: albedo rgb
    "white": (0.80, 0.80, 0.80), "black": (0.03, 0.03, 0.03), "silver": (0.55, 0.56, 0.58),
    "grey": (0.28, 0.29, 0.30), "red": (0.55, 0.04, 0.04), "blue": (0.05, 0.12, 0.45),
    "dark_blue": (0.02, 0.04, 0.15), "green": (0.08, 0.30, 0.10), "yellow": (0.75, 0.62, 0.05),
    "beige": (0.60, 0.52, 0.40),
}
PAINT_BASE = 32  # material id of the first paint
PAINT_NAMES = tuple(PAINTS)
ID = {name: i for i, (name, *_rest) in enumerate(_BASE)}


def paint_reflectivity(rgb: tuple[float, float, float]) -> float:
    """905 nm reflectivity of a car paint from its visible albedo (red pigments reflect NIR)."""
    r, g, b = rgb
    return float(0.05 + 0.55 * (0.5 * r + 0.3 * g + 0.2 * b) / 0.8 + 0.15 * max(r - g, 0.0))


def _tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = PAINT_BASE + len(PAINTS)
    refl = np.zeros(n, np.float32)
    albedo = np.zeros((n, 3), np.float32)
    emission = np.zeros((n, 3), np.float32)
    for i, (_name, rho, rgb, em) in enumerate(_BASE):
        refl[i], albedo[i], emission[i] = rho, rgb, em
    for j, rgb in enumerate(PAINTS.values()):
        refl[PAINT_BASE + j] = paint_reflectivity(rgb)
        albedo[PAINT_BASE + j] = rgb
    return refl, albedo, emission


REFLECTIVITY, ALBEDO, EMISSION = _tables()  # indexed by material id
REFLECTIVITY64 = REFLECTIVITY.astype(np.float64)
GROUND = np.zeros(len(REFLECTIVITY), bool)
GROUND[[ID["asphalt"], ID["lane_marking"], ID["gravel"], ID["grass"]]] = True
ROAD = np.zeros(len(REFLECTIVITY), bool)
ROAD[[ID["asphalt"], ID["lane_marking"]]] = True


def paint_id(name: str) -> int:
    return PAINT_BASE + PAINT_NAMES.index(name)


def lidar_tables(material: np.ndarray, actor: np.ndarray, vehicles: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The LiDAR's view of the vehicle triangles: (material ids (T,), reflectivity table (float64), ground table).

    A vehicle with a reflectance override (``Vehicle.reflectance``, 905 nm) has its paint triangles moved
    to a material of its own, appended after the shared table; the camera keeps the paint's albedo. Without
    overrides the inputs and the shared tables come back unchanged."""
    over = [(i, v) for i, v in enumerate(vehicles) if v.reflectance is not None]
    if not over:
        return material, REFLECTIVITY64, GROUND
    lidar_mat = material.copy()
    for k, (i, v) in enumerate(over):
        lidar_mat[(actor == i) & (material == paint_id(v.paint))] = len(REFLECTIVITY) + k
    refl = np.concatenate([REFLECTIVITY64, [float(v.reflectance) for _, v in over]])
    return lidar_mat, refl, np.concatenate([GROUND, np.zeros(len(over), bool)])
