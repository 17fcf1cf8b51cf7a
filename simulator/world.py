"""The static highway world as one triangle soup with a material id per triangle."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from simulator.materials import ID
from simulator.prims import UNIT_BLOB, UNIT_BOX, UNIT_CONE, UNIT_PRISM, place, quad_grid
from simulator.road import RoadConfig, road_to_world


@dataclass
class World:
    """Static geometry: triangles (T, 3, 3) float32 world metres, material (T,) uint8."""

    triangles: np.ndarray
    material: np.ndarray
    road: RoadConfig


class _Builder:
    def __init__(self) -> None:
        self.parts: list[np.ndarray] = []
        self.mats: list[np.ndarray] = []

    def add(self, tris: np.ndarray, material: str) -> None:
        self.parts.append(tris)
        self.mats.append(np.full(len(tris), ID[material], np.uint8))

    def build(self, road: RoadConfig) -> World:
        return World(np.concatenate(self.parts).astype(np.float32), np.concatenate(self.mats), road)


def sweep(cfg: RoadConfig, s: np.ndarray, profile: np.ndarray) -> np.ndarray:
    """Triangles of a (d, z) profile polyline (P, 2) swept along the road at arc lengths s."""
    ss = np.repeat(s, len(profile))
    dd = np.tile(profile[:, 0], len(s))
    x, y, _ = road_to_world(cfg, ss, dd)
    v = np.stack([x, y, np.tile(profile[:, 1], len(s))], 1).reshape(len(s), len(profile), 3)
    return quad_grid(v)


def _along(cfg: RoadConfig, s: np.ndarray, d: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World centres (B, 3) and headings (B,) of road points."""
    x, y, h = road_to_world(cfg, s, d)
    return np.stack([x, y, z], 1), h


def _road_surface(b: _Builder, cfg: RoadConfig, s: np.ndarray) -> None:
    edge = cfg.lanes_outer_edge + cfg.hard_shoulder
    b.add(sweep(cfg, s, np.array([[-edge, 0.0], [edge, 0.0]])), "asphalt")
    g = cfg.guardrail_offset + 0.5
    for sign in (-1, 1):
        b.add(sweep(cfg, s, np.array([[sign * edge, 0.0], [sign * g, 0.02]])[:: sign]), "gravel")


def _markings(b: _Builder, cfg: RoadConfig, s: np.ndarray) -> None:
    z = 0.01
    for sign in (-1, 1):
        for d in (cfg.lanes_inner_edge, cfg.lanes_outer_edge):  # solid edge lines
            dd = sign * d
            b.add(sweep(cfg, s, np.array([[dd - 0.12, z], [dd + 0.12, z]])), "lane_marking")
        for k in range(1, cfg.lanes):  # dashed 6 m / 12 m
            dd = sign * (cfg.lanes_inner_edge + k * cfg.lane_width)
            for s0 in np.arange(0.0, cfg.length - 6.0, 18.0):
                b.add(sweep(cfg, np.array([s0, s0 + 6.0]), np.array([[dd - 0.075, z], [dd + 0.075, z]])),
                      "lane_marking")


def _barriers(b: _Builder, cfg: RoadConfig, s: np.ndarray) -> None:
    m = cfg.median_half_width
    jersey = np.array([[-m, 0.0], [-0.75 * m, 0.25], [-0.25 * m, 0.82], [0.25 * m, 0.82], [0.75 * m, 0.25], [m, 0.0]])
    b.add(sweep(cfg, s, jersey), "concrete")
    g = cfg.guardrail_offset
    for sign in (-1, 1):
        b.add(sweep(cfg, s, np.array([[sign * g, 0.45], [sign * g, 0.78]])), "guardrail")
        ps = np.arange(1.0, cfg.length, 4.0)
        c, h = _along(cfg, ps, np.full(len(ps), sign * (g + 0.1)), np.full(len(ps), 0.375))
        b.add(place(UNIT_BOX, c, np.array([0.12, 0.12, 0.75]), h), "guardrail")
        ds = np.arange(25.0, cfg.length, 50.0)
        dd = sign * (cfg.lanes_outer_edge + cfg.hard_shoulder + 0.2)
        c, h = _along(cfg, ds, np.full(len(ds), dd), np.full(len(ds), 0.5))
        b.add(place(UNIT_BOX, c, np.array([0.1, 0.12, 1.0]), h), "delineator")


def _poles_and_signs(b: _Builder, cfg: RoadConfig) -> None:
    ls = np.arange(20.0, cfg.length, 60.0)
    c, h = _along(cfg, ls, np.zeros(len(ls)), np.full(len(ls), 5.0 + 0.82))
    b.add(place(UNIT_PRISM, c, np.array([0.22, 0.22, 10.0]), h), "metal_pole")
    for sign in (-1, 1):
        c, h = _along(cfg, ls, np.full(len(ls), sign * 1.5), np.full(len(ls), 10.7))
        b.add(place(UNIT_BOX, c, np.array([0.5, 3.0, 0.15]), h), "metal_pole")
    out = cfg.lanes_outer_edge + cfg.hard_shoulder + 1.5
    for sign in (-1, 1):
        ss = np.arange(130.0, cfg.length, 240.0)
        for dy in (-1.2, 1.2):
            c, h = _along(cfg, ss, np.full(len(ss), sign * (out + 1.2) + dy), np.full(len(ss), 1.75))
            b.add(place(UNIT_PRISM, c, np.array([0.12, 0.12, 3.5]), h), "metal_pole")
        c, h = _along(cfg, ss, np.full(len(ss), sign * (out + 1.2)), np.full(len(ss), 3.4))
        b.add(place(UNIT_BOX, c, np.array([0.08, 3.2, 1.8]), h), "sign_face")
    gs = np.array([cfg.straight_length + 150.0])
    for d in (-(out + 0.5), -0.8):
        c, h = _along(cfg, gs, np.array([d]), np.array([3.25]))
        b.add(place(UNIT_BOX, c, np.array([0.4, 0.4, 6.5]), h), "metal_pole")
    c, h = _along(cfg, gs, np.array([-(out + 1.3) / 2]), np.array([6.0]))
    b.add(place(UNIT_BOX, c, np.array([0.3, out, 1.6]), h), "sign_face")


def _terrain(b: _Builder, cfg: RoadConfig, rng: np.random.Generator) -> None:
    s = np.arange(-60.0, cfg.length + 60.0, 6.0)
    g0 = cfg.guardrail_offset + 0.5
    d = g0 + np.concatenate([[0.0, 2.0], np.geomspace(4.0, 130.0, 22)])
    k = rng.uniform(0.01, 0.05, (4, 2))
    ph = rng.uniform(0, 2 * np.pi, (4, 2))
    for sign in (-1, 1):
        S, D = np.meshgrid(s, d, indexing="ij")
        bump = sum(np.sin(k[i, 0] * S + ph[i, 0]) * np.sin(k[i, 1] * D + ph[i, 1]) for i in range(4))
        rise = np.clip(D - g0 - 2.0, 0, None)
        z = 0.02 + np.where(rise > 0, 0.06 * rise * np.exp(-rise / 40.0) + 0.6 * bump * np.minimum(rise / 10.0, 1.0), 0.0)
        x, y, _ = road_to_world(cfg, S, sign * D)
        grid = np.stack([x, y, z], -1)
        b.add(quad_grid(grid if sign < 0 else grid[:, ::-1]), "grass")


def _vegetation(b: _Builder, cfg: RoadConfig, rng: np.random.Generator, n_trees: int = 220, n_bushes: int = 160) -> None:
    g = cfg.guardrail_offset
    for sign in (-1, 1):
        s = rng.uniform(-40.0, cfg.length + 40.0, n_trees)
        d = sign * (g + 5.0 + rng.gamma(2.0, 12.0, n_trees))
        hgt = rng.uniform(5.0, 12.0, n_trees)
        c, h = _along(cfg, s, d, hgt * 0.2)
        b.add(place(UNIT_PRISM, c, np.stack([np.full(n_trees, 0.3), np.full(n_trees, 0.3), hgt * 0.4], 1), h), "wood")
        c[:, 2] = hgt * 0.3
        crown = np.stack([hgt * 0.45, hgt * 0.45, hgt * 0.75], 1)
        b.add(place(UNIT_CONE, c, crown, rng.uniform(0, 6.3, n_trees)), "foliage")
        s = rng.uniform(-40.0, cfg.length + 40.0, n_bushes)
        d = sign * (g + 1.5 + rng.gamma(1.5, 8.0, n_bushes))
        size = rng.uniform(0.8, 2.5, (n_bushes, 1)) * np.array([[1.2, 1.0, 0.7]])
        c, h = _along(cfg, s, d, size[:, 2] * 0.4)
        b.add(place(UNIT_BLOB, c, size, rng.uniform(0, 6.3, n_bushes)), "foliage")
        n_rocks = 60
        s = rng.uniform(0.0, cfg.length, n_rocks)
        d = sign * (g + rng.uniform(0.6, 4.0, n_rocks))
        size = rng.uniform(0.2, 0.7, (n_rocks, 3))
        c, h = _along(cfg, s, d, size[:, 2] * 0.4)
        b.add(place(UNIT_BOX, c, size, rng.uniform(0, 6.3, n_rocks)), "concrete")


def _noise_wall(b: _Builder, cfg: RoadConfig, rng: np.random.Generator) -> None:
    s0 = rng.uniform(150.0, cfg.length - 350.0)
    s = np.arange(s0, s0 + 180.0, 5.0)
    d = cfg.guardrail_offset + 2.5
    b.add(sweep(cfg, s, np.array([[d, 0.0], [d, 3.5]])), "concrete")


def build_world(cfg: RoadConfig, rng: np.random.Generator) -> World:
    """All static geometry of the highway; clutter positions drawn from rng."""
    b = _Builder()
    s = np.arange(-60.0, cfg.length + 60.0, 4.0)
    _road_surface(b, cfg, s)
    _markings(b, cfg, s)
    _barriers(b, cfg, s)
    _poles_and_signs(b, cfg)
    _terrain(b, cfg, rng)
    _vegetation(b, cfg, rng)
    _noise_wall(b, cfg, rng)
    return b.build(cfg)
