"""Where a training step's time goes: a torch.profiler profile of each model's step (default
profile, one thread, after warm-up), split into GEMM/conv, sparse gather/scatter, sparse rule
building, voxelisation, point ops, RoI pooling, target assignment, losses, NMS in training, data
loading + augmentation, optimizer and the rest; and the seconds per step without the profiler.

    python -m benchmarks.profile_train_step --data DIR [--models a,b] [--warmup 2] [--steps 4] [--amp bf16]

A step is what one training process spends per batch on one core (glibc malloc keeping freed
memory, as in ``harness.malloc``): reading and augmenting the
batch's frames (``harness.train.load_batch``, ground-truth sampling for LiDAR-only models), the
forward and loss, backward, gradient clipping and AdamW. Batches are those of epoch 0 of seed 0.
With ``--amp bf16`` the forward and loss run under the training's autocast (``harness.amp``), as with
``train --amp bf16``.

Attribution: the functions in ``REGISTRY`` are wrapped in ``record_function`` for the profiled
steps; an op's own time goes to the innermost wrapped function around it (a backward op to that
of the forward op that made its autograd node), GEMM and convolution kernels to "GEMM/conv"
wherever they run. Python and numpy time inside a wrapped function is that function's. The
profiler's own overhead inflates many-small-op code; the "s/step" column is timed without it.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import importlib
import inspect
import re
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile, record_function

from harness.augment import AugmentConfig, augment
from harness.dataset import KittiDataset
from harness.gt_database import load_or_build
from harness.malloc import keep_freed_memory
from harness.train import uses_gt_sampling
from models import zoo

GEMM = "GEMM/conv"
CATEGORIES = (GEMM, "sparse gather/scatter", "sparse rules", "voxelise + VFE", "point ops", "RoI pooling",
              "targets", "losses", "NMS (train)", "data + augment", "optimizer", "other")

# (module, function or Class.method, category): the innermost one around an op takes its time
REGISTRY = (
    ("models.sparse", "_PairGemm.forward", "sparse gather/scatter"),
    ("models.sparse", "_PairGemm.backward", "sparse gather/scatter"),
    ("models.sparse", "table_gemm", "sparse gather/scatter"),
    ("models.sparse", "to_dense", "sparse gather/scatter"),
    ("models.sparse", "height_compress", "sparse gather/scatter"),
    ("models.backbone2d", "scatter_to_bev", "sparse gather/scatter"),
    ("models.sparse", "pair_gemm", "sparse rules"),
    ("models.sparse", "subm_table", "sparse rules"),
    ("models.sparse", "strided_out_coords", "sparse rules"),
    ("models.sparse", "strided_table", "sparse rules"),
    ("models.sparse", "inverse_table", "sparse rules"),
    ("models.voxelize", "hard_voxelize", "voxelise + VFE"),
    ("models.voxelize", "dynamic_voxelize", "voxelise + VFE"),
    ("models.vfe", "MeanVFE.forward", "voxelise + VFE"),
    ("models.vfe", "PillarVFE.forward", "voxelise + VFE"),
    ("models.mvx_net", "FusionVFE.forward", "voxelise + VFE"),
    ("models.pointnet2", "farthest_point_sample", "point ops"),
    ("models.pointnet2", "ball_queries", "point ops"),
    ("models.pointnet2", "ball_query", "point ops"),
    ("models.pointnet2", "group_points", "point ops"),
    ("models.pointnet2", "three_nn_interpolate", "point ops"),
    ("models.point_rcnn", "PointRCNN.points_of_interest", "point ops"),
    ("models.roi_pool", "roiaware_pool", "RoI pooling"),
    ("models.roi_pool", "RoIGridPool.forward", "RoI pooling"),
    ("models.point_roi_pool", "roi_point_pool", "RoI pooling"),
    ("models.parta2", "roi_sparse_grid", "RoI pooling"),
    ("models.parta2", "roi_dense_grid", "RoI pooling"),
    ("models.anchor_head", "assign_targets", "targets"),
    ("models.parta2", "part_targets", "targets"),
    ("models.pv_rcnn", "keypoint_targets", "targets"),
    ("models.point_rcnn", "PointRCNN.seg_targets", "targets"),
    ("models.point_rcnn", "encode_bins", "targets"),
    ("models.roi_head", "sample_rois", "targets"),
    ("models.roi_head", "encode_canonical", "targets"),
    ("models.losses", "sigmoid_focal_loss", "losses"),
    ("models.losses", "box_regression_loss", "losses"),
    ("models.losses", "direction_loss", "losses"),
    ("models.point_rcnn", "bin_loss", "losses"),
    ("models.roi_head", "refine_loss", "losses"),
    ("models.roi_head", "propose", "NMS (train)"),
    ("models.point_rcnn", "PointRCNN.propose", "NMS (train)"),
)
_PREFIX = "cat::"


def _wrap(fn, category: str):
    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with record_function(_PREFIX + category):
            return fn(*args, **kwargs)
    return wrapped


def instrument() -> None:
    """Wrap every ``REGISTRY`` function, wherever ``models`` / ``harness`` modules hold it."""
    for module_name, qualname, category in REGISTRY:
        module = importlib.import_module(module_name)
        if "." in qualname:  # a method: replaced on its class
            cls_name, attr = qualname.split(".")
            cls = getattr(module, cls_name)
            raw = cls.__dict__[attr]
            fn = raw.__func__ if isinstance(raw, staticmethod) else raw
            wrapped = _wrap(fn, category)
            setattr(cls, attr, staticmethod(wrapped) if isinstance(raw, staticmethod) else wrapped)
            continue
        original = getattr(module, qualname)
        wrapped = _wrap(original, category)
        for name, mod in list(sys.modules.items()):
            if name.split(".")[0] in ("models", "harness") and getattr(mod, qualname, None) is original:
                setattr(mod, qualname, wrapped)


_GEMM_OPS = re.compile(r"(conv(?!ert)|^aten::(mm|addmm|bmm|baddbmm|addmv|mv|matmul|linear|_addmm_activation)$|"
                       r"^autograd::engine::evaluate_function: (Mm|Addmm|Bmm|Mv|Convolution)\w*Backward)")


def _enclosing(event, forward_category: dict) -> str | None:
    """The category of ``event``: GEMM/conv inside a GEMM or convolution op (its copies and fills
    too), else that of the innermost wrapped function or annotation around it."""
    e = event
    while e is not None:
        if _GEMM_OPS.search(e.name):
            return GEMM
        if e.name.startswith(_PREFIX):
            return e.name[len(_PREFIX):]
        if e.name.startswith("autograd::engine::evaluate_function"):
            return forward_category.get(e.sequence_nr)
        e = e.cpu_parent
    return None


def attribute(events) -> dict[str, float]:
    """Seconds of each category summed over ``events`` (own time of every event)."""
    forward_category = {}
    for e in events:  # the forward op that recorded each autograd node, by sequence number
        if e.sequence_nr >= 0 and not e.name.startswith("autograd::") and e.sequence_nr not in forward_category:
            forward_category[e.sequence_nr] = _enclosing(e.cpu_parent, {})  # the op's own name: not GEMM
    totals = dict.fromkeys(CATEGORIES, 0.0)
    for e in events:
        cat = _enclosing(e, forward_category) or "other"
        totals[cat if cat in totals else "other"] += e.self_cpu_time_total * 1e-6
    return totals


def step_autocast(amp: str):
    """The training step's autocast of ``amp`` ("" none)."""
    if not amp:
        return contextlib.nullcontext()
    from harness.amp import autocast  # imported only when asked for: paired_train_step runs this file on older code too
    return autocast(amp)


class Stepper:
    """One model's training steps on the batches of epoch 0 (seed 0), as ``harness.train`` takes them
    (``amp``: under that autocast, as ``Schedule.amp``)."""

    def __init__(self, name: str, data: Path, amp: str = ""):
        torch.manual_seed(0)
        self.amp = amp
        self.net = zoo.build(name, "compact")
        self.net.train()
        self.net.sampling_rng = np.random.default_rng([0, 0, 1])
        if "keep" in inspect.signature(KittiDataset).parameters:  # as harness.train reads them (older code: from disk)
            self.ds = KittiDataset(data, "train", with_image=self.net.uses_camera, keep=True)
            for i in range(len(self.ds)):  # the epochs after the first: every frame read before
                self.ds[i]
        else:
            self.ds = KittiDataset(data, "train", with_image=self.net.uses_camera)
        self.aug = AugmentConfig()
        self.database = (load_or_build(data, data / "gt_database", self.aug.gt_sampling)
                         if uses_gt_sampling(self.net, self.aug) else None)
        self.tcfg = zoo.resolve(name, "compact").schedule
        # the one-cycle schedule's first rate (harness.train: div_factor 10), that of a training's first steps
        self.optimizer = torch.optim.AdamW(self.net.parameters(), lr=self.tcfg.lr / 10,
                                           weight_decay=self.tcfg.weight_decay)
        self.order = np.random.default_rng([0, 0]).permutation(len(self.ds))

    def step(self, k: int) -> float:
        """Step ``k`` (its batch and draws); returns its loss."""
        bs = self.tcfg.batch_size
        frames = self.order[(k * bs) % len(self.ds):][:bs]
        with record_function(_PREFIX + "other"):  # Python time outside every op and wrapped function
            with record_function(_PREFIX + "data + augment"):
                rng = np.random.default_rng([0, 0, k])  # as harness.train.load_batch (absent from older code)
                samples = [augment(self.ds[int(i)], rng, self.aug, self.database) for i in frames]
            with step_autocast(self.amp):
                loss = self.net.loss(samples)["loss"]
            loss.backward()
            with record_function(_PREFIX + "optimizer"):
                torch.nn.utils.clip_grad_norm_(self.net.parameters(), self.tcfg.grad_clip)
                self.optimizer.step()
                self.optimizer.zero_grad(set_to_none=True)
        return float(loss.detach())


def seconds_per_step(stepper: Stepper, first: int, steps: int) -> float:
    t0 = time.perf_counter()
    for k in range(first, first + steps):
        stepper.step(k)
    return (time.perf_counter() - t0) / steps


def profile_model(name: str, data: Path, warmup: int, steps: int, amp: str = "") -> tuple[dict[str, float], float]:
    """Seconds per step of each category (profiled) and the unprofiled seconds per step, both
    over the same ``steps`` batches after ``warmup`` steps."""
    stepper = Stepper(name, data, amp)
    seconds_per_step(stepper, 0, warmup)
    state = {k: v.clone() for k, v in stepper.net.state_dict().items()}
    opt_state = stepper.optimizer.state_dict()
    rng_state = stepper.net.sampling_rng.bit_generator.state
    plain = seconds_per_step(stepper, warmup, steps)
    stepper.net.load_state_dict(state)  # the profiled steps repeat the timed ones
    stepper.optimizer.load_state_dict(opt_state)
    stepper.net.sampling_rng.bit_generator.state = rng_state
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        seconds_per_step(stepper, warmup, steps)
    return {k: v / steps for k, v in attribute(prof.events()).items()}, plain


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, required=True, help="a training set (sotif-bench simulate --preset train)")
    p.add_argument("--models", default=",".join(zoo.MODEL_NAMES))
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--steps", type=int, default=4)
    p.add_argument("--amp", choices=["bf16"], help="steps under the training's autocast (train --amp)")
    p.add_argument("--serve", action="store_true", help="for paired_train_step: after the warm-up of the one "
                   "model, read step numbers from stdin and print each step's seconds and loss")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    keep_freed_memory()  # as the training processes of `train` and `run` do
    if args.serve:
        stepper = Stepper(args.models, args.data, args.amp or "")
        if args.warmup:  # --warmup 0: the steps served are a training's first
            seconds_per_step(stepper, 0, args.warmup)
        print("ready", flush=True)
        for line in sys.stdin:
            start = time.perf_counter()
            loss = stepper.step(int(line))
            print(time.perf_counter() - start, loss, flush=True)
        return 0
    instrument()
    short = [c.split(" (")[0] for c in CATEGORIES]
    print("| model | s/step | profiled s/step | " + " | ".join(short) + " | GEMM share |")
    print("|---|" + "---:|" * (len(CATEGORIES) + 3))
    for name in args.models.split(","):
        cats, plain = profile_model(name, args.data, args.warmup, args.steps, args.amp or "")
        total = sum(cats.values())
        cells = " | ".join(f"{100 * cats[c] / total:.0f} %" for c in CATEGORIES)
        print(f"| {name} | {plain:.2f} | {total:.2f} | {cells} | {100 * cats[GEMM] / total:.0f} % |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
