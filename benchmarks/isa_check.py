"""Does a seed give the same data set on every CPU? Three measurements, printed:

1. Embree's raw output per instruction set: the HDL-64E pattern cast over the highway with Embree
   devices pinned to AVX-512, AVX2 and SSE4.2 (ctypes on the library embreex ships; embreex makes
   its own device and takes no configuration): rays whose tfar, Ng or hit triangle differ. And (1b)
   rays aimed at the highway's vertices and edges, cast with every ISA the CPU runs: Embree's own
   triangle against the one the ray caster settles from that ISA's candidates.
2. Fused multiply-adds in the simulator's compiled (numba) code: none means its arithmetic is plain
   IEEE and the same on every x86-64 CPU with the same compiler flags.
3. The golden cases of tests/simulator/test_golden.py made in a subprocess that runs as another CPU
   would: numpy's AVX-512 kernels off (NPY_DISABLE_CPU_FEATURES), numba compiling for Haswell or Zen 2,
   OpenBLAS's Haswell or Zen kernels, and Embree's tfar / Ng moved by a few ulp: files that differ.

    python -m benchmarks.isa_check [--poses 3]
"""
from __future__ import annotations

import argparse
import ctypes as C
import glob
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
EMULATED = {"haswell": {"NUMBA_CPU_NAME": "haswell", "OPENBLAS_CORETYPE": "Haswell"},
            "zen2": {"NUMBA_CPU_NAME": "znver2", "OPENBLAS_CORETYPE": "Zen"}}
NUMPY_AVX2 = "X86_V4 AVX512_ICL AVX512_SPR"  # numpy 2.x names of its AVX-512 dispatch targets


class _RayHit(C.Structure):  # RTCRayHit of Embree 4 (one instance level): RTCRay (48 bytes), RTCHit
    _fields_ = ([(n, C.c_float) for n in "ox oy oz tnear dx dy dz time tfar".split()]
                + [("mask", C.c_uint), ("id", C.c_uint), ("flags", C.c_uint)]
                + [(n, C.c_float) for n in "ngx ngy ngz u v".split()]
                + [("prim", C.c_uint), ("geom", C.c_uint), ("inst", C.c_uint), ("instprim", C.c_uint),
                   ("pad2", C.c_uint * 8)])


def _embree():
    import embreex
    lib = C.CDLL(glob.glob(str(Path(embreex.__file__).parent.parent / "embreex.libs" / "libembree4*.so*"))[0])
    for f, res, args in (("rtcNewDevice", C.c_void_p, [C.c_char_p]), ("rtcNewScene", C.c_void_p, [C.c_void_p]),
                         ("rtcNewGeometry", C.c_void_p, [C.c_void_p, C.c_int]),
                         ("rtcSetNewGeometryBuffer", C.c_void_p,
                          [C.c_void_p, C.c_int, C.c_uint, C.c_int, C.c_size_t, C.c_size_t]),
                         ("rtcAttachGeometry", C.c_uint, [C.c_void_p, C.c_void_p]),
                         ("rtcIntersect1", None, [C.c_void_p, C.POINTER(_RayHit), C.c_void_p])):
        getattr(lib, f).restype, getattr(lib, f).argtypes = res, args
    for f in ("rtcCommitGeometry", "rtcCommitScene", "rtcReleaseGeometry"):
        getattr(lib, f).argtypes = [C.c_void_p]
    return lib


def ulp_noise(run, rng: np.random.Generator):
    """``run`` (the settling's Embree call) with its tfar moved by up to 4 ulp and Ng by up to 1e-6 relative, as
    other SIMD kernels give them."""
    def noisy(scene, origins, dirs, max_t=1e37):
        res = run(scene, origins, dirs, max_t)
        hit = res["primID"] >= 0
        t = res["tfar"].copy()
        t[hit] += rng.integers(-4, 5, hit.sum()).astype(np.float32) * np.spacing(t[hit])
        res["tfar"] = t
        res["Ng"] = (res["Ng"] * (1 + rng.uniform(-1e-6, 1e-6, res["Ng"].shape))).astype(np.float32)
        return res
    return noisy


def embree_cast(lib, isa: str, tris: np.ndarray, origin: np.ndarray, dirs: np.ndarray):
    """tfar (N,), Ng (N, 3), hit triangle (N,) (-1: miss) from an Embree device pinned to ``isa``."""
    dev = lib.rtcNewDevice(f"isa={isa},threads=1".encode())
    scene, geo = lib.rtcNewScene(dev), lib.rtcNewGeometry(dev, 0)  # RTC_GEOMETRY_TYPE_TRIANGLE
    n = len(tris)
    vb = lib.rtcSetNewGeometryBuffer(geo, 1, 0, 0x9003, 12, 3 * n)  # vertex buffer, FLOAT3
    C.memmove(vb, np.ascontiguousarray(tris.reshape(-1, 3), np.float32).ctypes.data, 36 * n)
    ib = lib.rtcSetNewGeometryBuffer(geo, 0, 0, 0x5003, 12, n)  # index buffer, UINT3
    C.memmove(ib, np.arange(3 * n, dtype=np.uint32).ctypes.data, 12 * n)
    lib.rtcCommitGeometry(geo), lib.rtcAttachGeometry(scene, geo), lib.rtcReleaseGeometry(geo)
    lib.rtcCommitScene(scene)
    t, ng, prim, rh = np.empty(len(dirs), np.float32), np.empty((len(dirs), 3), np.float32), np.empty(len(dirs), int), _RayHit()
    for i, d in enumerate(dirs.astype(np.float32)):
        rh.ox, rh.oy, rh.oz = (float(v) for v in origin)
        rh.dx, rh.dy, rh.dz = (float(v) for v in d)
        rh.tnear, rh.tfar, rh.mask, rh.flags, rh.time, rh.geom = 0.0, float("inf"), 0xFFFFFFFF, 0, 0.0, 0xFFFFFFFF
        lib.rtcIntersect1(scene, C.byref(rh), None)
        t[i], ng[i], prim[i] = rh.tfar, (rh.ngx, rh.ngy, rh.ngz), rh.prim if rh.geom != 0xFFFFFFFF else -1
    return t, ng, prim


def embree_by_isa(poses: int) -> None:
    from simulator.lidar import LidarSpec, ray_directions
    from simulator.road import RoadConfig
    from simulator.world import build_world
    lib, tris = _embree(), build_world(RoadConfig(), np.random.default_rng(0)).triangles
    dirs = ray_directions(LidarSpec())
    print(f"1. Embree by ISA: {len(dirs)} rays of the HDL-64E pattern x {poses} poses over {len(tris)} triangles")
    for k in range(poses):
        origin = np.array([150.0 + 200.0 * k, -5.0, 1.73])
        ref = embree_cast(lib, "avx512", tris, origin, dirs)
        for isa in ("avx2", "sse4.2"):
            t, ng, prim = embree_cast(lib, isa, tris, origin, dirs)
            hit = ref[2] >= 0
            dt = np.abs(t[hit].astype(np.float64) - ref[0][hit])
            print(f"   pose {k} {isa:7s} vs avx512: {hit.sum()} hits; tfar differs on {(dt > 0).sum()} "
                  f"(max {dt.max():.2e} m), Ng on {(ng != ref[1]).any(1).sum()}, hit triangle on {(prim != ref[2]).sum()}")


def isas() -> list[str]:
    """The Embree ISAs this CPU runs, best first."""
    flags = Path("/proc/cpuinfo").read_text().split()
    return [isa for isa, flag in (("avx512", "avx512f"), ("avx2", "avx2"), ("avx", "avx"), ("sse4.2", "sse4_2"),
                                  ("sse2", "sse2")) if flag in flags]


def rays_at_edges(tris: np.ndarray, origin: np.ndarray, rng: np.random.Generator, n: int) -> np.ndarray:
    """Unit directions from origin at the triangles' vertices, edge points and a few random points."""
    k = rng.integers(0, len(tris), n)
    e = rng.integers(0, 3, n)
    f = rng.uniform(0, 1, n)[:, None]
    v = tris.astype(np.float64)
    pts = v[k, e] * f + v[k, (e + 1) % 3] * (1 - f)
    pts[: n // 4] = v[k[: n // 4], e[: n // 4]]
    pts[n - n // 8:] += rng.normal(0, 0.5, (n // 8, 3))
    d = pts - origin
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def settle_by_isa(lib, mesh, origin: np.ndarray, dirs: np.ndarray, isas_: list[str]) -> dict:
    """{isa: (Embree's own triangle, the settled one)} per ray (float32 unit dirs from origin), Embree pinned to
    each ISA: its own cast of the mesh's triangles, and its candidates on the grown ones settled (settling.settle)."""
    import simulator.settling as settling
    o32 = np.ascontiguousarray(np.broadcast_to(origin.astype(np.float32), dirs.shape))
    out = {}
    for isa in isas_:
        raw = embree_cast(lib, isa, mesh.triangles, origin, dirs)[2]
        cand = embree_cast(lib, isa, settling.grown(mesh.triangles), origin, dirs)[2].astype(np.int64)
        out[isa] = raw, settling.settle(mesh.triangles, mesh.planes, mesh.bounds, mesh.region, *mesh.grid, mesh.pad,
                                        cand, o32, dirs, np.full(len(dirs), 1e37))
    return out


def settled_by_isa(n: int = 20000) -> None:
    """The settled triangle (settling.settle on the candidates of Embree pinned to each ISA, on the grown
    triangles) against Embree's own answer, for rays aimed at the highway's vertices and edges."""
    import simulator.settling as settling
    from simulator.road import RoadConfig
    from simulator.world import build_world
    tris = build_world(RoadConfig(), np.random.default_rng(0)).triangles
    origin = np.array([300.0, -5.0, 1.9])
    near = np.flatnonzero(np.linalg.norm(tris.mean(1) - origin, axis=1) < 80)
    dirs = rays_at_edges(tris[near], origin, np.random.default_rng(3), n).astype(np.float32)
    out = settle_by_isa(_embree(), settling.Mesh(tris), origin, dirs, isas())
    best = next(iter(out))
    print(f"1b. Settled hits by ISA: {n} rays aimed at the highway's vertices and edges")
    for isa, (raw, settled) in out.items():
        print(f"   {isa:7s} vs {best}: Embree's triangle differs on {(raw != out[best][0]).sum()}, "
              f"the settled one on {(settled != out[best][1]).sum()}")


def fma_in_numba() -> None:
    code = ("import importlib, pkgutil, tempfile; from pathlib import Path; import numba, simulator\n"
            "from simulator import generate\n"
            "generate(Path(tempfile.mkdtemp()) / 's', progress=False, preset='sotif', frames=2, "
            "weathers='HardRainNight', seed=3, instances=1)\n"
            "n = f = 0\n"
            "for m in pkgutil.iter_modules(simulator.__path__):\n"
            "    mod = importlib.import_module('simulator.' + m.name)\n"
            "    for fn in vars(mod).values():\n"
            "        if isinstance(fn, numba.core.registry.CPUDispatcher) and fn.__module__ == mod.__name__:\n"
            "            for asm in fn.inspect_asm().values():\n"
            "                n += 1; f += any(o in asm for o in ('vfmadd', 'vfmsub', 'vfnmadd', 'vfnmsub'))\n"
            "print(f'2. numba: {n} compiled functions of simulator/, {f} with a fused multiply-add')\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": tempfile.mkdtemp()}  # compiled now, so the assembly can be read
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, check=True)


def golden_as(cpu: str) -> None:
    code = ("import json, sys, tempfile; from pathlib import Path; import numpy as np\n"
            "import simulator.settling as settling\n"
            "from tests.simulator.test_golden import CASES, GOLDEN, digests\n"
            "from simulator import generate\n"
            "from benchmarks.isa_check import ulp_noise\n"
            "settling.embree_cast = ulp_noise(settling.embree_cast, np.random.default_rng(7))\n"
            "for name, kw in sorted(CASES.items()):\n"
            "    kw = dict(kw, **({'instances': 1} if kw['preset'] == 'sotif' else {}))\n"
            "    got = digests(generate(Path(tempfile.mkdtemp()) / name, progress=False, **kw))\n"
            "    bad = [k for k in GOLDEN[name] if got.get(k) != GOLDEN[name][k]]\n"
            "    print(f'   {name}: {len(got)} files, {len(bad)} differ from the golden digests', bad[:5])\n")
    env = {**os.environ, **EMULATED[cpu], "NPY_DISABLE_CPU_FEATURES": NUMPY_AVX2,
           "NUMBA_CACHE_DIR": tempfile.mkdtemp(), "PYTHONPATH": str(ROOT)}
    print(f"3. golden cases as {cpu}: {json.dumps(EMULATED[cpu])}, numpy without {NUMPY_AVX2}, Embree +-4 ulp")
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, check=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=3)
    a = ap.parse_args()
    embree_by_isa(a.poses)
    settled_by_isa()
    fma_in_numba()
    for cpu in EMULATED:
        golden_as(cpu)


if __name__ == "__main__":
    main()
