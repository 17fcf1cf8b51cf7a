"""How little PointRCNN's point operators can cost in onnxruntime, against its GEMM time.

Issue 29 asks, on one thread, for non-GEMM time <= GEMM time for every model. PointRCNN's GEMMs
are small (about 1.7 GFLOP a frame: under 20 ms at this CPU's GEMM peak), and its point
operators are sequential or quadratic. This script times, one thread, CPU time, best of several
runs, each operator in the graph form the model exports and the least that operator can do in
standard ONNX ops:

- farthest point sampling 8192 -> 512 (and PointRCNN's three later levels): a Loop of 512 steps.
  Floor: a step that only updates N distances (Min) and takes their ArgMax, the distances
  themselves given for free; and a Loop step whose body is one Add.
- the first set abstraction's ball queries (512 centres among 8192 points, PointRCNN's two
  radii). Floor: per radius one comparison of the (512, 8192) distances with r^2 and one TopK
  of ``nsample`` per row (the first ``nsample`` indices within the radius).
- the last feature propagation's 3-NN search (8192 points among 512). Floor: TopK of 3 per row.
- the RoI point pooling (64 RoIs, the first 128 points inside each). Floor: TopK of 128 per row.

The sum of the floors, next to the GEMM time of the whole exported model (random weights: the
shapes, hence the FLOPs, are those of a trained one) at the GEMM peak measured in the same run:

    python -m benchmarks.op_floors [--data DIR] [--repeats 7]

``--data``: a data set whose first SOTIF-like frame is used (default: one simulated frame).
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch
from onnx import TensorProto, helper
from torch._higher_order_ops.while_loop import while_loop

from benchmarks.ort_profile import cpu_ms, gemm_peak, profile_frames, session
from harness.core import kitti
from models.pointnet2 import ball_queries, fps_loop, three_nn_interpolate


def exported(module: torch.nn.Module, args: tuple, dims: tuple, folder: Path, name: str) -> ort.InferenceSession:
    path = folder / f"{name}.onnx"
    torch.onnx.export(module.eval(), args, str(path), dynamo=True, dynamic_shapes=dims, optimize=True, verbose=False)
    return session(path, threads=1)


def one_op(node, inputs: list, outputs: list) -> ort.InferenceSession:
    graph = helper.make_graph([node], "op", inputs, outputs)
    proto = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    return session(proto.SerializeToString(), threads=1)


def topk_ms(rows: int, cols: int, k: int, repeats: int) -> float:
    """One TopK of ``k`` smallest over (rows, cols) float32."""
    sess = one_op(helper.make_node("TopK", ["x", "k"], ["v", "i"], largest=0, sorted=1),
                  [helper.make_tensor_value_info("x", TensorProto.FLOAT, [rows, cols]),
                   helper.make_tensor_value_info("k", TensorProto.INT64, [1])],
                  [helper.make_tensor_value_info("v", TensorProto.FLOAT, [rows, k]),
                   helper.make_tensor_value_info("i", TensorProto.INT64, [rows, k])])
    x = np.random.default_rng(0).random((rows, cols), np.float32)
    return cpu_ms(sess, {"x": x, "k": np.array([k], np.int64)}, repeats)


def less_ms(rows: int, cols: int, repeats: int) -> float:
    """One comparison of (rows, cols) float32 with a scalar."""
    sess = one_op(helper.make_node("Less", ["x", "r"], ["y"]),
                  [helper.make_tensor_value_info("x", TensorProto.FLOAT, [rows, cols]),
                   helper.make_tensor_value_info("r", TensorProto.FLOAT, [1])],
                  [helper.make_tensor_value_info("y", TensorProto.BOOL, [rows, cols])])
    x = np.random.default_rng(0).random((rows, cols), np.float32)
    return cpu_ms(sess, {"x": x, "r": np.array([0.5], np.float32)}, repeats)


class Fps(torch.nn.Module):
    def __init__(self, num: int):
        super().__init__()
        self.num = num

    def forward(self, xyz):
        return fps_loop(xyz[None], self.num)[0]


class FpsFloor(torch.nn.Module):
    """The least an FPS step does: min-update N given distances, ArgMax (512 steps)."""

    def __init__(self, num: int):
        super().__init__()
        self.num = num

    def forward(self, d0):
        def cond(i, d, last):
            return i < self.num

        def body(i, d, last):
            # the step's pick scales the given distances by 1 + 1e-9 * index: the body depends on it
            d = torch.minimum(d, d0 * (1.0 + last.to(torch.float32) * 1e-9))
            return i + 1, d, torch.argmax(d).reshape(1)

        start = (torch.zeros((), dtype=torch.long), d0 + 1.0, torch.zeros(1, dtype=torch.long))
        return while_loop(cond, body, start)[2]


class EmptyLoop(torch.nn.Module):
    def __init__(self, num: int):
        super().__init__()
        self.num = num

    def forward(self, x):
        def cond(i, a):
            return i < self.num

        def body(i, a):
            return i + 1, a + 1.0

        return while_loop(cond, body, (torch.zeros((), dtype=torch.long), x.sum().reshape(1)))[1]


class BallQueries(torch.nn.Module):
    def __init__(self, radii, nsamples):
        super().__init__()
        self.radii, self.nsamples = radii, nsamples

    def forward(self, xyz, centres):
        return tuple(idx for idx, _ in ball_queries(xyz, centres, self.radii, self.nsamples))


class ThreeNN(torch.nn.Module):
    def forward(self, unknown, known, feats):
        return three_nn_interpolate(unknown, known, feats)


def frame_points(data: Path | None, folder: Path) -> np.ndarray:
    if data is None:
        from simulator.dataset import generate
        data = generate(folder / "sotif", preset="sotif", frames=1, seed=0, progress=False)
    first = sorted((Path(data) / "training" / "velodyne").glob("*.bin"))[0]
    return kitti.read_points(first)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, help="a data set (default: one simulated SOTIF frame)")
    p.add_argument("--repeats", type=int, default=7)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    from models.export import export_onnx
    from models.point_rcnn import CONFIGS, PointRCNN

    cfg = CONFIGS["compact"]
    rep = args.repeats
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        points = frame_points(args.data, folder)
        peak = gemm_peak()
        torch.manual_seed(0)
        model = PointRCNN(cfg).eval()
        export_onnx(model, folder / "point_rcnn.onnx", {"sotif.profile": "compact"})
        prof = profile_frames(folder / "point_rcnn.onnx", [{"points": points}] * 3)
        whole = cpu_ms(session(folder / "point_rcnn.onnx", threads=1), {"points": points}, 3)
        gemm_at_peak = prof["gemm_gflop"] / peak * 1000.0

        inside = points[(points[:, 0] > cfg.pc_range[0]) & (points[:, 0] < cfg.pc_range[3])][:, :3]
        rng = np.random.default_rng(0)
        xyz = np.ascontiguousarray(inside[rng.choice(len(inside), cfg.num_points, replace=len(inside) < cfg.num_points)])
        n = torch.export.Dim("n")
        m = torch.export.Dim("m")
        rows = []

        # farthest point sampling, every level of the backbone
        fps_graph = fps_floor = 0.0
        sizes = (cfg.num_points, *cfg.sa_npoints)
        d0 = ((xyz - xyz[0]) ** 2).sum(1).astype(np.float32)
        for level, (src, num) in enumerate(zip(sizes[:-1], sizes[1:])):
            sess = exported(Fps(num), (torch.randn(src, 3),), ({0: n},), folder, f"fps{level}")
            fps_graph += cpu_ms(sess, {"xyz": xyz[:src]}, rep)
            sess = exported(FpsFloor(num), (torch.ones(src),), ({0: n},), folder, f"fpsfloor{level}")
            fps_floor += cpu_ms(sess, {"d0": d0[:src]}, rep)
        empty = cpu_ms(exported(EmptyLoop(sizes[1]), (torch.zeros(4, 3),), ({0: n},), folder, "empty"),
                       {"x": xyz[:4]}, rep)
        rows.append(("farthest point sampling, backbone levels " + " -> ".join(map(str, sizes)), fps_graph, fps_floor,
                     f"Min + ArgMax only; a {sizes[1]}-step Loop whose body is one Add: {empty:.2f} ms"))

        # first set abstraction: ball queries
        radii, nsamples = cfg.sa_radii[0], cfg.sa_nsamples[0]
        centres = xyz[: cfg.sa_npoints[0]]
        sess = exported(BallQueries(radii, nsamples), (torch.randn(cfg.num_points, 3), torch.randn(cfg.sa_npoints[0], 3)),
                        ({0: n}, {0: m}), folder, "ballq")
        bq = cpu_ms(sess, {"xyz": xyz, "centres": centres}, rep)
        bq_floor = sum(less_ms(len(centres), len(xyz), rep) + topk_ms(len(centres), len(xyz), k, rep) for k in nsamples)
        rows.append((f"ball queries, {len(centres)} centres among {len(xyz)} points, radii {radii}", bq, bq_floor,
                     "per radius: one Less and one TopK of nsample per row"))

        # last feature propagation: 3-NN among the first level's centres
        feats = rng.random((cfg.sa_npoints[0], cfg.fp_mlps[0][-1]), np.float32)
        sess = exported(ThreeNN(), (torch.randn(cfg.num_points, 3), torch.randn(cfg.sa_npoints[0], 3),
                                    torch.randn(cfg.sa_npoints[0], feats.shape[1])),
                        ({0: n}, {0: m}, {0: m}), folder, "threenn")
        nn3 = cpu_ms(sess, {"unknown": xyz, "known": centres, "feats": feats}, rep)
        rows.append((f"3-NN interpolation, {len(xyz)} points among {len(centres)}", nn3,
                     topk_ms(len(xyz), len(centres) + 3, 3, rep), "one TopK of 3 per row"))

        # RoI point pooling: the first pool_samples points inside each RoI
        pool_floor = topk_ms(cfg.rois, cfg.num_points + cfg.pool_samples, cfg.pool_samples, rep)
        rows.append((f"RoI point pooling, {cfg.rois} RoIs x first {cfg.pool_samples} of {cfg.num_points} points", None,
                     pool_floor, "one TopK of pool_samples per row"))

    print(f"GEMM peak (onnxruntime MatMul 2048^2, one thread): {peak:.1f} GFLOP/s")
    print(f"PointRCNN (compact, random weights): GEMM {prof['gemm_gflop']:.2f} GFLOP a frame = "
          f"{gemm_at_peak:.1f} ms at the peak; the whole graph {whole:.1f} ms, its GEMM nodes {prof['gemm_ms']:.1f} ms")
    print()
    print("| operator | graph form ms | floor ms | floor = |")
    print("|---|---|---|---|")
    for name, graph, floor, what in rows:
        print(f"| {name} | {'' if graph is None else f'{graph:.1f}'} | {floor:.1f} | {what} |")
    total = sum(r[2] for r in rows)
    print()
    print(f"sum of the floors: {total:.1f} ms against {gemm_at_peak:.1f} ms of GEMMs at the peak "
          f"({'above' if total > gemm_at_peak else 'below'})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
