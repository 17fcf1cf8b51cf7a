"""The simulator's bytes do not depend on the instruction set.

Embree's kernels differ by ISA (SSE, AVX2, AVX-512) and by CPU vendor in the last bits of tfar and Ng, and
for rays that pass within rounding of an edge in the triangle hit. The ray caster keeps none of it: it
settles the triangle and recomputes distance and normal itself in float64 (settling.settle, exact_hits;
tests/simulator/test_raycast_settle.py moves the rays Embree sees), so a data set made from Embree output
perturbed by a few ulp, as another CPU's kernels would give it, is byte-identical."""
import numpy as np
import pytest

import simulator.raycast as raycast
import simulator.settling as settling
from benchmarks.isa_check import ulp_noise
from simulator import generate
from tests.simulator.test_golden import digests


def _plane_hit_reference(tri: np.ndarray, o: np.ndarray, d: np.ndarray) -> float:
    """Distance along d from o to the triangle's plane: solve o + t d = v0 + u e1 + v e2 (numpy)."""
    v0, v1, v2 = tri.astype(np.float64)
    a = np.stack([d, -(v1 - v0), -(v2 - v0)], 1)
    return float(np.linalg.solve(a, v0 - o)[0])


def test_exact_hits_against_a_linear_solve():
    rng = np.random.default_rng(0)
    tris = rng.uniform(-5, 5, (50, 3, 3)).astype(np.float32)
    prim = rng.integers(-1, 50, 400).astype(np.int32)
    origins = rng.uniform(-20, 20, (400, 3)).astype(np.float32)
    centroid = tris[np.maximum(prim, 0)].astype(np.float64).mean(1)
    d = centroid - origins
    dirs = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    tfar = np.full(400, 7.0, np.float32)
    t, ng = settling.exact_hits(tris, prim, origins, dirs, tfar)
    for i in range(400):
        if prim[i] < 0:
            assert t[i] == 7.0 and not ng[i].any()
            continue
        tri = tris[prim[i]].astype(np.float64)
        normal = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        np.testing.assert_allclose(ng[i], normal, rtol=1e-6, atol=1e-6)
        if abs(dirs[i] @ normal) < 0.1 * np.linalg.norm(normal):
            continue  # a grazing ray: both solutions are ill-conditioned
        want = _plane_hit_reference(tris[prim[i]], origins[i].astype(np.float64), dirs[i].astype(np.float64))
        assert t[i] == pytest.approx(want, rel=1e-6)  # float32 rounding of a float64 result


def test_cast_agrees_with_embree_away_from_edges(highway_scene):
    rng = np.random.default_rng(1)
    az, el = rng.uniform(-np.pi, np.pi, 2000), rng.uniform(-0.4, 0.02, 2000)
    dirs = np.c_[np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
    origin = np.array([300.0, -5.0, 1.9])
    hits = highway_scene.cast(origin, dirs)
    tris = np.concatenate([highway_scene.world.triangles, *highway_scene.vehicle_triangles])  # the shared scene's
    ref = raycast.first_hit_distance(tris, np.broadcast_to(origin, dirs.shape), dirs)  # vehicles, if any are set
    assert np.isfinite(hits.t).sum() > 1500
    np.testing.assert_array_equal(np.isfinite(hits.t), np.isfinite(ref))
    np.testing.assert_allclose(hits.t[np.isfinite(ref)], ref[np.isfinite(ref)], rtol=1e-5, atol=1e-4)


@pytest.fixture
def ulp_noise_embree(monkeypatch):
    """Embree's tfar moved by up to 4 ulp and Ng by 1e-6 relative, as other SIMD kernels give them."""
    monkeypatch.setattr(settling, "embree_cast", ulp_noise(settling.embree_cast, np.random.default_rng(123)))


@pytest.mark.parametrize("kwargs", [dict(preset="train", frames=2, seed=5),
                                    dict(preset="sotif", frames=2, weathers="HardRainNight", seed=3, instances=1)])
def test_embree_last_bits_do_not_reach_the_files(tmp_path, kwargs, request):
    plain = digests(generate(tmp_path / "plain", progress=False, **kwargs))
    request.getfixturevalue("ulp_noise_embree")
    noisy = digests(generate(tmp_path / "noisy", progress=False, **kwargs))
    assert any(k.startswith("training/velodyne/") for k in plain)
    assert [k for k in plain if plain[k] != noisy.get(k)] == []
