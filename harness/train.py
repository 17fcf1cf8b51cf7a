"""Generic detector training: KITTI folders -> augmented Samples -> ``model.loss`` -> AdamW with a
one-cycle schedule -> ``<out>/checkpoint.pt``.

The loop knows no model: it calls ``model.loss(list[Sample])`` only, so one-stage, two-stage and
camera models (``uses_camera`` -> images and lidar2img loaded) train through the same function.

Checkpoint (written atomically after every epoch; an existing one of the same model, profile,
data and config is resumed): ``model``, ``profile``, ``config`` (asdict), ``state_dict``,
``epoch`` (completed epochs), ``epochs``, ``optimizer``, ``scheduler``, ``data_hash``,
``config_hash``, ``final_loss``, ``train_seconds`` (summed over resumed sessions), ``seed``, and
``val_history``: after every epoch, the loss, the machine it ran on (``harness.provenance.machine``: a
rerun on another CPU is another draw) and the val AP40 on the first ``EPOCH_VAL_FRAMES`` val
frames (the convergence check: has the schedule reached its plateau?). After the last epoch,
``val_ap`` scores all val frames.
"""
from __future__ import annotations

import io
import math
import os
import shutil
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from datetime import timedelta
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch.optim.swa_utils import AveragedModel
from tqdm import tqdm

from harness.amp import autocast, check_amp
from harness.augment import AugmentConfig, augment
from harness.core.files import atomic_write_bytes
from harness.dataset import KittiDataset, config_hash, dataset_hash, has_split
from harness.gt_database import load_or_build
from harness.provenance import machine
from models import zoo
from models.base import Detector
from models.recipe import ModelRecipe, Schedule

EMA_WARMUP = 10.0  # decay at update n: min(decay, (1 + n) / (EMA_WARMUP + n)), TensorFlow ExponentialMovingAverage's num_updates


EPOCH_VAL_FRAMES = 20  # val frames scored after every epoch (a few seconds to a minute per model)


def _resolved(model: str | ModelRecipe, profile: str | None, warm: bool = False) -> ModelRecipe:
    """``model`` as resolved by a run, or a model name resolved in ``profile`` (default compact)."""
    if not isinstance(model, ModelRecipe):
        return zoo.resolve(model, profile or "compact", warm=warm)
    if profile not in (None, model.profile):
        raise ValueError(f"{model.model} is resolved for profile {model.profile!r}, not {profile!r}")
    return model


def _atomic_save(obj, path: Path) -> None:
    buf = io.BytesIO()
    torch.save(obj, buf)
    atomic_write_bytes(path, buf.getvalue())


def _build(recipe: ModelRecipe, seed: int) -> torch.nn.Module:
    """The model initialised from ``seed`` without touching the global RNG state."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return recipe.build()


def _resume(path: Path, net, optimizer, scheduler, ident: dict, ema: AveragedModel | None = None
            ) -> tuple[int, float, list]:
    """Completed epochs, training seconds and val history of a matching checkpoint at ``path``
    ((0, 0.0, []) when absent / not matching); the network, optimizer, schedule and weight average
    ``ema`` go on from its state."""
    if not path.is_file():
        return 0, 0.0, []
    ckpt = zoo.read_checkpoint(path)
    if any(ckpt.get(k) != v for k, v in ident.items()):
        return 0, 0.0, []  # another model, data set or config: start again
    if ema is not None:
        net.load_state_dict(ckpt["train_state_dict"])
        ema.module.load_state_dict(ckpt["state_dict"])
        ema.n_averaged.fill_(int(ckpt["ema_updates"]))
    else:
        net.load_state_dict(ckpt["state_dict"])
    optimizer.load_state_dict(ckpt["optimizer"])
    scheduler.load_state_dict(ckpt["scheduler"])
    return int(ckpt["epoch"]), float(ckpt.get("train_seconds") or 0.0), list(ckpt.get("val_history") or [])


def _replaceable_checkpoint(path: Path, model: str, force: bool) -> None:
    """Refuse a file at ``path`` that is not a checkpoint of ``model`` (another model's, or no
    checkpoint that loads safely), unless ``force``: then it is removed unread."""
    if not path.is_file():
        return
    try:
        other = zoo.read_checkpoint(path).get("model")
        found = None if other == model else f"is a checkpoint of {other!r}"
    except zoo.CheckpointError as e:
        found = str(e).removeprefix(f"{path}: ")
    if found and not force:
        raise ValueError(f"{path}: {found}; training {model!r} into {path.parent} would replace it "
                         "(pass --force to replace it, or choose another --out)")
    if found:
        path.unlink()


def _batches(n: int, batch_size: int, seed: int, epoch: int) -> list[np.ndarray]:
    order = np.random.default_rng([seed, epoch]).permutation(n)
    return [order[i:i + batch_size] for i in range(0, n, batch_size)]


def load_batch(ds: KittiDataset, frames, rng: np.random.Generator, aug: AugmentConfig = AugmentConfig(),
               database=None) -> list:
    """The frames ``frames`` of ``ds``, read and augmented in order with the draws of ``rng``."""
    return [augment(ds[int(i)], rng, aug, database) for i in frames]


def ema_decay(decay: float, updates: int) -> float:
    """The weight average's decay at its update number ``updates`` (0 for the first after the copy): ``decay``,
    lower at first so that the average forgets the initial weights within a few hundred steps."""
    return min(decay, (1.0 + updates) / (EMA_WARMUP + updates))


def weight_average(net: torch.nn.Module, decay: float) -> AveragedModel | None:
    """The exponential moving average of ``net``'s parameters and buffers (BatchNorm statistics), or None when
    ``decay`` is 0: torch's ``AveragedModel`` with ``ema_decay``'s warm-up; ``update_parameters(net)`` after every
    optimizer step."""
    if not decay:
        return None

    def average(avg: torch.Tensor, new: torch.Tensor, updates: torch.Tensor) -> torch.Tensor:
        return avg + (new - avg) * (1.0 - ema_decay(decay, int(updates) - 1))
    return AveragedModel(net, avg_fn=average, use_buffers=True)


def _run_epoch(net, ds, optimizer, scheduler, tcfg: Schedule, seed: int, epoch: int, bar,
               aug: AugmentConfig = AugmentConfig(), database=None, rank: int = 0, world: int = 1,
               ema: AveragedModel | None = None) -> float:
    """One epoch; with ``world`` > 1 data-parallel workers, this one (``rank``) takes the frames
    ``rank::world`` of every batch and the step is taken on the gradients summed over all of them.
    ``ema``: the weight average, updated after every step. The forward pass and loss run under ``tcfg.amp``'s
    autocast (``harness.amp``); the backward pass, clipping and step in the weights' float32."""
    net.train()
    losses = []
    batches = _batches(len(ds), tcfg.batch_size, seed, epoch)
    own = [] if world == 1 else [rank]  # a worker's draws are its own; a single process keeps the old ones

    def load(step: int) -> list:
        rng = np.random.default_rng([seed, epoch, step, *own])  # a step's augmentation draws: its own generator
        return load_batch(ds, batches[step][rank::world], rng, aug, database)

    # the RoI heads' dropout draws from torch's global generator and their RoI sampling from the
    # model's own: seed both per epoch (and leave the caller's torch state alone), so that a
    # training is repeatable and a resumed epoch draws as before
    with torch.random.fork_rng(devices=[]), ThreadPoolExecutor(1) as loader:
        torch.manual_seed(int(np.random.default_rng([seed, epoch, *own]).integers(2 ** 62)))
        net.sampling_rng = np.random.default_rng([seed, epoch, 1, *own])
        pending = loader.submit(load, 0) if batches else None
        for step in range(len(batches)):
            samples = pending.result()
            if step + 1 < len(batches):  # read and augment the next batch while this one trains
                pending = loader.submit(load, step + 1)
            optimizer.zero_grad(set_to_none=True)
            if world == 1:
                with autocast(tcfg.amp):
                    loss = net.loss(samples)["loss"]
                loss.backward()
                value = float(loss.detach())
            else:
                value = _data_parallel_backward(net, samples, len(batches[step]), tcfg.amp)
            if not math.isfinite(value):  # before the step: the weights stay those of the last good one
                frames = ", ".join(ds.frame_ids[int(i)] for i in batches[step])
                raise ValueError(f"{ds.root}: the training loss is {value} at epoch {epoch + 1}, step {step + 1} "
                                 f"(frames {frames}): the weights diverged or these frames hold values the network "
                                 "cannot take; the checkpoint of the last finished epoch is kept")
            torch.nn.utils.clip_grad_norm_(net.parameters(), tcfg.grad_clip)
            optimizer.step()
            scheduler.step()
            if ema is not None:
                ema.update_parameters(net)
            losses.append(value)
            bar.update(1)
            bar.set_postfix(epoch=epoch + 1, loss=f"{np.mean(losses[-20:]):.3f}")
    return float(np.mean(losses)) if losses else math.nan


def _data_parallel_backward(net, samples: list, batch_frames: int, amp: str = "") -> float:
    """Backward of this worker's ``samples``, then the all-reduce that gives every worker the
    gradient of the whole batch (each worker's weighted by its share of the batch's frames, so
    the sum is the mean over the batch's frames, as in one process), the BatchNorm running
    statistics weighted alike, and the batch's loss. All replicas then take the same step."""
    share = len(samples) / batch_frames
    counters = [b for b in net.buffers() if not b.is_floating_point()]  # BatchNorm num_batches_tracked
    before = [b.clone() for b in counters]
    value = 0.0
    if samples:  # the last batch of an odd frame count leaves a worker without frames
        with autocast(amp):
            loss = net.loss(samples)["loss"]
        loss.backward()
        value = float(loss.detach())
    params = [p for p in net.parameters() if p.requires_grad]
    stats = [b for b in net.buffers() if b.is_floating_point()]
    parts = [(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) * share for p in params]
    parts += [b.reshape(-1) * share for b in stats]
    parts += [(b - s).reshape(-1).float() for b, s in zip(counters, before)]
    parts.append(torch.tensor([float(p.grad is not None) for p in params] + [value * share], device=parts[0].device))
    flat = torch.cat(parts)
    dist.all_reduce(flat)
    offset = 0
    for p in params:
        p.grad = flat[offset:offset + p.numel()].view_as(p).clone()
        offset += p.numel()
    for b in stats:
        b.copy_(flat[offset:offset + b.numel()].view_as(b))
        offset += b.numel()
    for b, s in zip(counters, before):
        b.copy_(s + flat[offset:offset + b.numel()].view_as(b).round().to(b.dtype))
        offset += b.numel()
    for p, used in zip(params, flat[offset:offset + len(params)].tolist()):
        if not used:  # no worker's frames reached it: no gradient, as in one process
            p.grad = None
    return float(flat[-1])


def eager_inputs(sample, camera: bool, device="cpu") -> list[torch.Tensor]:
    """A dataset sample as the eager model's arguments: points, and for a camera model the image
    batch of one and lidar2img."""
    inputs = [torch.as_tensor(sample.points, device=device)]
    if camera:
        inputs += [torch.as_tensor(sample.image[None], device=device), torch.as_tensor(sample.lidar2img, device=device)]
    return inputs


def validation_ap(net, data: Path, max_frames: int | None = None, split: str = "val",
                  groups: dict[str, str] | None = None, frame_ids: list[str] | None = None) -> dict:
    """AP40 (3D / BEV, IoU 0.7) of the eager model on the ``split`` split (default ``val``; ``frame_ids``: these
    frames instead) with the project's KITTI evaluator: KITTI moderate and the headline (all distances, height
    filter off; and per distance bin, ``3d_all_distance``). With ``groups`` (frame id -> group name, e.g. the
    precipitation class) also the headline 3D AP of each group's frames (``3d_all_by``)."""
    from harness.eval_kitti import build_eval_set, kitti_ap
    from harness.evaluate import headline_summary
    from harness.infer import boxes_to_results

    ds = KittiDataset(data, split, with_image=getattr(net, "uses_camera", False), frame_ids=frame_ids)
    n = len(ds) if max_frames is None else min(len(ds), max_frames)
    gt, dt = [], []
    net.eval()
    device = next(net.parameters()).device
    with torch.no_grad():
        for i in range(n):
            out = net(*eager_inputs(ds[i], net.uses_camera, device))
            calib = ds.calib(i)
            gt.append(ds.labels(i))
            dt.append(boxes_to_results(out[0].cpu().numpy(), out[1].cpu().numpy(), calib, (375, 1242)))
    es = build_eval_set(gt, dt)
    ap = kitti_ap(es)
    summary = headline_summary(es)
    head = summary["headline"]
    out = {"3d_moderate": ap["3d"]["0.7"]["R40"]["moderate"], "bev_moderate": ap["bev"]["0.7"]["R40"]["moderate"],
           "3d_all": head["3d"]["0.7"], "bev_all": head["bev"]["0.7"], "frames": n,
           "3d_all_distance": summary["distance"]["3d"]["0.7"]}
    if groups is not None:
        names = [groups[f] for f in ds.frame_ids[:n]]
        out["3d_all_by"] = {g: headline_summary(build_eval_set([gt[i] for i in range(n) if names[i] == g],
                                                               [dt[i] for i in range(n) if names[i] == g]))
                            ["headline"]["3d"]["0.7"] for g in sorted(set(names))}
    return out


def uses_gt_sampling(net: Detector, aug: AugmentConfig) -> bool:
    """Ground-truth sampling for LiDAR-only models; camera models go without it (the pasted
    objects would not be in the image)."""
    return aug.gt_sampling.enabled and not net.uses_camera


def default_workers(model: str | ModelRecipe, profile: str | None = None, device: str = "cpu") -> int:
    """Data-parallel workers of ``sotif-bench train``: one per core, at most one per frame of a
    batch (on the CPU; a CUDA device trains in one process)."""
    if device != "cpu" or launched_world() > 1:  # under torchrun every process is one worker
        return 1
    return max(1, min(_resolved(model, profile).schedule.batch_size, os.cpu_count() or 1))


def launched_world() -> int:
    """The number of processes of the torchrun launch this process belongs to (1 outside one)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def _fit_launched(s: _Session, seed: int, aug: AugmentConfig, progress: bool, device: str) -> dict | None:
    """This process's part of a torchrun launch (env:// rendezvous; RANK and WORLD_SIZE from the
    launcher, on one machine or several): ``_fit`` as one data-parallel worker, exactly as the
    ``workers`` that ``--workers`` spawns. Rank 0 writes the checkpoint; returns its last state."""
    rank, world = int(os.environ["RANK"]), launched_world()
    dist.init_process_group("nccl" if device == "cuda" else "gloo", init_method="env://",
                            timeout=timedelta(minutes=30))
    try:
        with _bar(s, progress and rank == 0) as bar:
            state = _fit(s, seed, aug, bar, rank, world)
        dist.barrier()  # the checkpoint is written before any process goes on
    finally:
        dist.destroy_process_group()
    return state


@dataclass
class _Session:
    """What a training needs, set up alike in every data-parallel worker."""
    recipe: ModelRecipe
    net: torch.nn.Module
    ds: KittiDataset
    database: object
    tcfg: Schedule
    ident: dict
    state: dict  # config, epochs, seed: the checkpoint's fixed entries
    optimizer: torch.optim.Optimizer
    scheduler: object
    path: Path
    done: int  # epochs completed before this call
    spent: float  # training seconds before this call
    steps: int
    history: list  # val_history of the completed epochs
    ema: AveragedModel | None = None  # the weight average (Schedule.ema), what is evaluated and checkpointed

    @property
    def evaluated(self) -> torch.nn.Module:
        """The weights a training gives: the average's, or the network's own without one."""
        return self.net if self.ema is None else self.ema.module

    def weights(self) -> dict:
        """The checkpoint's weight entries: ``state_dict`` (evaluated and exported) and, with an average, the
        network's own ``train_state_dict`` and the average's ``ema_updates`` (a resumed training goes on from them)."""
        if self.ema is None:
            return {"state_dict": self.net.state_dict()}
        own = {k: v.clone() for k, v in self.net.state_dict().items()}  # the net may be loaded with the average
        return {"state_dict": self.ema.module.state_dict(), "train_state_dict": own,
                "ema_updates": int(self.ema.n_averaged)}


def _session(recipe: ModelRecipe, data: Path, out: Path, epochs: int | None, seed: int,
             aug: AugmentConfig, init_from: Path | None = None) -> _Session:
    cfg, tcfg = recipe.config, recipe.schedule
    # an explicit epoch count is the schedule: `--epochs 8` and a profile of 8 epochs train alike
    tcfg = replace(tcfg, epochs=tcfg.epochs if epochs is None else int(epochs))
    epochs = tcfg.epochs
    if epochs < 1:
        raise ValueError(f"epochs must be >= 1, got {epochs}")
    net = _build(recipe, seed)
    warm = {}  # a sibling's first stage, part of the identity: a changed sibling is another training
    if init_from is not None:  # the weights it brought in, not the file (whose training time differs on a rerun)
        loaded, _ = zoo.warm_start(net, recipe, init_from)
        own = net.state_dict()
        warm = {"warm_start": {"init_weights": zoo.weights_digest({n: own[n] for n in loaded}),
                               "warm_tensors": len(loaded)}}
    ds = KittiDataset(data, "train", with_image=net.uses_camera, keep=True)  # read once, augmented every epoch
    if len(ds) == 0:
        raise ValueError(f"{data / 'ImageSets' / 'train.txt'}: no training frames")
    use_gts = uses_gt_sampling(net, aug)
    database = load_or_build(data, data / "gt_database", aug.gt_sampling) if use_gts else None
    ident = {"model": recipe.model, "profile": recipe.profile, "data_hash": dataset_hash(data),
             "config_hash": config_hash({"model": asdict(cfg), "train": tcfg.key(), "epochs": epochs,
                                         "seed": seed, "augment": asdict(aug), "gt_sampling": use_gts, **warm})}
    optimizer = torch.optim.AdamW(net.parameters(), lr=tcfg.lr, weight_decay=tcfg.weight_decay)
    steps = epochs * math.ceil(len(ds) / tcfg.batch_size)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(optimizer, max_lr=tcfg.lr, total_steps=steps,
                                                    pct_start=0.4, div_factor=10, final_div_factor=100)
    path = out / "checkpoint.pt"
    ema = weight_average(net, tcfg.ema)
    done, spent, history = _resume(path, net, optimizer, scheduler, ident, ema)  # spent: s before this call
    return _Session(recipe, net, ds, database, tcfg, ident,
                    {"config": asdict(cfg), "epochs": epochs, "seed": seed, **warm},
                    optimizer, scheduler, path, done, spent, steps, history, ema)


def _bar(s: _Session, show: bool) -> tqdm:
    return tqdm(total=s.steps, initial=s.done * (s.steps // s.tcfg.epochs),
                desc=f"train {s.recipe.model}/{s.recipe.profile}", disable=not show, unit="step")


def _fit(s: _Session, seed: int, aug: AugmentConfig, bar, rank: int = 0, world: int = 1,
         on_epoch=None) -> dict | None:
    """The remaining epochs; rank 0 writes the checkpoint after each and calls
    ``on_epoch(epochs done, epochs, mean seconds of this call's epochs)``. Returns the last state."""
    start, state, checking = time.perf_counter(), None, 0.0  # checking: seconds of the val checks
    for epoch in range(s.done, s.tcfg.epochs):
        loss = _run_epoch(s.net, s.ds, s.optimizer, s.scheduler, s.tcfg, seed, epoch, bar, aug, s.database,
                          rank=rank, world=world, ema=s.ema)
        if rank == 0:
            t = time.perf_counter()
            s.history.append(_epoch_check(s, epoch, loss, bar))
            checking += time.perf_counter() - t
            seconds = s.spent + time.perf_counter() - start - checking
            state = {**s.ident, **s.state, **s.weights(), "epoch": epoch + 1,
                     "optimizer": s.optimizer.state_dict(), "scheduler": s.scheduler.state_dict(),
                     "final_loss": loss, "train_seconds": seconds, "workers": world, "val_history": s.history}
            _atomic_save(state, s.path)
            if on_epoch is not None:
                on_epoch(epoch + 1, s.tcfg.epochs, (time.perf_counter() - start) / (epoch + 1 - s.done))
    return state


def _epoch_check(s: _Session, epoch: int, loss: float, bar) -> dict:
    """The epoch's entry of ``val_history``: its mean loss, the machine it ran on and, when the data has a val split, the
    val AP40 on its first ``EPOCH_VAL_FRAMES`` frames (one line on the progress bar)."""
    entry = {"epoch": epoch + 1, "loss": loss, "machine": machine()}  # another CPU: another draw
    if has_split(s.ds.root, "val"):
        ap = validation_ap(s.evaluated, s.ds.root, EPOCH_VAL_FRAMES)
        entry.update({k: ap[k] for k in ("3d_moderate", "bev_moderate", "3d_all", "frames")})
        if not bar.disable:
            bar.write(f"epoch {epoch + 1}/{s.tcfg.epochs}: loss {loss:.3f}, val AP40 3D moderate "
                      f"{ap['3d_moderate']:.2f} on the first {ap['frames']} val frames")
    return entry


def convergence_line(history: list) -> str:
    """``val_history`` in one line: val AP40 3D moderate after each epoch."""
    aps = [f"{h['3d_moderate']:.1f}" for h in history if "3d_moderate" in h]
    if not aps:
        return "no val frames: no convergence check"
    return (f"val AP40 3D moderate after each epoch (first {history[-1]['frames']} val frames): "
            + " ".join(aps))


def _worker(rank: int, world: int, tmp: str, threads: int, parent: int, args: tuple, progress: bool) -> None:
    """Data-parallel worker ``rank`` (of ``world``, spawned by ``_fit_data_parallel``, which shares
    the folder ``tmp`` with it); rank 0 writes the checkpoint and shows the progress bar."""
    from harness.jobs import job_init
    job_init(threads, parent)
    recipe, data, out, epochs, seed, aug, init_from = args
    dist.init_process_group("gloo", init_method=f"file://{tmp}/store", rank=rank, world_size=world,
                            timeout=timedelta(minutes=30))
    try:
        s = _session(recipe, data, out, epochs, seed, aug, init_from)
        with _bar(s, progress and rank == 0) as bar:
            _fit(s, seed, aug, bar, rank, world)
    except (ValueError, OSError) as e:  # bad input (a malformed frame, say): the message goes to the caller
        atomic_write_bytes(Path(tmp) / f"error-{rank}", str(e).encode())
        raise
    finally:
        dist.destroy_process_group()


def _fit_data_parallel(s: _Session, workers: int, args: tuple, progress: bool) -> dict:
    """``_fit`` in ``workers`` spawned processes, each with its share of the cores, while this one
    watches them: a worker that fails ends the others and raises here with its error. Returns
    the checkpoint's state, also loaded into ``s.net``."""
    threads = max(1, (os.cpu_count() or 1) // workers)
    tmp = tempfile.mkdtemp(prefix="sotif-train-")
    ctx = None
    try:
        ctx = mp.start_processes(_worker, args=(workers, tmp, threads, os.getpid(), args, progress),
                                 nprocs=workers, join=False, start_method="spawn")
        while not ctx.join(timeout=1):  # raises ProcessRaisedException / ProcessExitedException
            pass
    except mp.ProcessRaisedException as e:
        errors = sorted(Path(tmp).glob("error-*"))
        if errors:  # a worker's bad input: raised here as such, with the worker's message
            raise ValueError(errors[0].read_text()) from e
        raise
    finally:
        if ctx is not None:
            for p in ctx.processes:
                if p.is_alive():
                    p.terminate()
                    p.join()
        shutil.rmtree(tmp, ignore_errors=True)
    state = zoo.read_checkpoint(s.path) if s.path.is_file() else {"epoch": 0}
    if state["epoch"] < s.tcfg.epochs:  # the workers were interrupted (SIGINT) and ended quietly
        raise KeyboardInterrupt(f"data-parallel training stopped after epoch {state['epoch']} of {s.tcfg.epochs}")
    s.net.load_state_dict(state["state_dict"])
    return state


def train(model: str | ModelRecipe, data: Path, out: Path, profile: str | None = None, epochs: int | None = None,
          device: str = "cpu", seed: int = 0, progress: bool = True, aug: AugmentConfig = AugmentConfig(),
          workers: int = 1, on_epoch=None, force: bool = False, init_from: Path | None = None) -> Path:
    """Train ``model`` on ``<data>/ImageSets/train.txt``; returns ``<out>/checkpoint.pt``. A file
    there that is not a checkpoint of ``model`` is refused, not replaced, unless ``force``.
    ``model``: the ModelRecipe a run resolved (``models.zoo.resolve``: network, config and schedule),
    or a model name, resolved here in ``profile`` (default compact; warm-started when ``init_from``).
    LiDAR-only models get ground-truth sampling (``aug.gt_sampling``, database cached in
    ``<data>/gt_database``); camera models do not (pasted objects are not in the image).

    ``workers`` > 1 trains data-parallel on the CPU (as OpenPCDet's distributed training does on
    GPUs): ``workers`` spawned processes (this one watches them), with the cores split among them,
    each run their share of every batch's frames, and an all-reduce (torch.distributed, gloo) sums the
    gradients before each step, so the replicas stay equal. Frames run one by one in every model
    (no batch axis), so the step is the one a single process takes, to rounding, on the same
    frames; the augmentation draws are per worker, and BatchNorm's running statistics are the
    workers' weighted mean. On 2 cores, 2 workers train PointPillars 1.33x as fast as one process
    with 2 threads, whose convolutions on one frame leave the second core half idle (docs/performance.md).
    ``on_epoch`` (one process only) is called after each epoch's checkpoint, as in ``_fit``.
    Under ``torchrun`` (several GPUs or machines) every launched process is one such worker.
    ``init_from``: a checkpoint of a sibling model whose matching weights start the training
    (``models.zoo.warm_start``); its digest is part of the training's identity.
    A schedule with ``amp`` (``harness.amp``) is refused, before any work, on a CPU without native bfloat16.
    """
    data, out = Path(data), Path(out)
    init_from = None if init_from is None else Path(init_from)
    recipe = _resolved(model, profile, warm=init_from is not None)
    batch_size = recipe.schedule.batch_size
    if not 1 <= workers <= batch_size:
        raise ValueError(f"workers must be between 1 and the batch size {batch_size}, got {workers}")
    world = launched_world()
    if world > 1 and workers > 1:
        raise ValueError(f"under torchrun every process is one data-parallel worker; got workers={workers}")
    if world > batch_size:
        raise ValueError(f"torchrun started {world} processes, more than the batch size {batch_size}")
    if workers > 1 and device != "cpu":
        raise ValueError(f"data-parallel workers train on the CPU; got workers={workers} with device {device!r}")
    if device == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device 'cuda' asked for, but torch {torch.__version__} sees no CUDA device here; "
                         "train with --device cpu")
    check_amp(recipe.schedule.amp, device)
    _replaceable_checkpoint(out / "checkpoint.pt", recipe.model, force)
    if world > 1 and device == "cuda":
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
    with torch.device(device):
        s = _session(recipe, data, out, epochs, seed, aug, init_from)
        s.net.to(device)
        if world > 1:
            state = _fit_launched(s, seed, aug, progress, device)
            if int(os.environ["RANK"]) != 0:
                return s.path
        elif workers > 1 and s.done < s.tcfg.epochs:
            state = _fit_data_parallel(s, workers, (recipe, data, out, epochs, seed, aug, init_from), progress)
        else:
            with _bar(s, progress) as bar:
                state = _fit(s, seed, aug, bar, on_epoch=on_epoch)
        if state is None and s.path.is_file():  # trained before; validated unless stopped just before it
            state = zoo.read_checkpoint(s.path, map_location=device)
            state = None if "val_ap" in state else state
        if state is not None and has_split(data, "val"):
            # held-out frames of the training generator, kept with the checkpoint; the weights evaluated are
            # the checkpoint's (the average's, with one)
            s.net.load_state_dict(state["state_dict"])
            ap = validation_ap(s.net, data)
            _atomic_save({**state, "val_ap": ap}, s.path)
            if progress:
                print(convergence_line(state.get("val_history") or []))
                print(f"val AP40 @0.7 ({ap['frames']} frames): 3D moderate {ap['3d_moderate']:.2f}, "
                      f"BEV moderate {ap['bev_moderate']:.2f}, 3D all-distance {ap['3d_all']:.2f}, "
                      f"BEV all-distance {ap['bev_all']:.2f}")
    return s.path
