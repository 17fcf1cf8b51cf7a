"""``sotif-bench import``: a published OpenPCDet or MMDetection3D checkpoint -> our checkpoint.

The file is read with ``torch.load(weights_only=True)`` (``models.zoo.read_checkpoint``: tensors
and plain data only, nothing in it runs). OpenPCDet saves ``model_state`` (with ``global_step``)
beside ``epoch``, ``it``, ``optimizer_state`` and ``version``; MMDetection3D saves ``meta`` and
``state_dict``, whose ``_metadata`` gives each module's version: a sparse conv of version 2 holds
spconv 2.x's layout. An OpenPCDet file has no such record, so its layout is the one that fits
every sparse conv's shape (a 4 -> 16 conv tells them apart; a 16 -> 16 conv cannot, which is why
the whole file must agree). Every tensor goes through the table of ``harness.published_maps``;
a tensor no rule takes, a tensor of ours no rule fills, or a shape that does not fit is an error
listing them, and nothing is written. The result is a checkpoint of our ``kitti`` profile
(``models.zoo.load_checkpoint`` reads it) with ``published`` = where the weights came from. A file
whose recorded classes are those of another published config of the network (``CLASS_CONFIGS``:
MMDetection3D's Car-only DV-SECOND) gets the ``kitti`` network with that config's head: only
those classes' anchor sets and channels, in the checkpoint's config.
"""
from __future__ import annotations

import dataclasses
import io
import re
from pathlib import Path

import torch

from harness.core.files import atomic_write_bytes, sha256_file
from harness.published_maps import CLASS_CONFIGS, CONFIG_FILES, FC, IGNORED, SPARSE, TABLES
from models import zoo

SOURCES = ("openpcdet", "mmdet3d")
SPCONV1, SPCONV2 = "spconv 1.x [kD, kH, kW, in, out]", "spconv 2.x [out, kD, kH, kW, in]"
LISTED = 12  # names an error message lists of each kind


class PublishedFileError(ValueError):
    """A published file that does not fit (message names the file and every problem)."""


def _names(names: list[str]) -> str:
    more = f" and {len(names) - LISTED} more" if len(names) > LISTED else ""
    return ", ".join(names[:LISTED]) + more


def read_published(path: Path, source: str) -> tuple[dict, dict, dict]:
    """(reference state dict, its module metadata, provenance) of a published file."""
    ckpt = zoo.read_checkpoint(path)
    if source == "openpcdet":
        state = ckpt.get("model_state")
        if not isinstance(state, dict):
            raise PublishedFileError(f"{path}: not an OpenPCDet checkpoint (no model_state; it holds "
                               f"{_names(sorted(map(str, ckpt)))})")
        return state, {}, {"version": str(ckpt.get("version", "")), "epoch": ckpt.get("epoch")}
    state, meta = ckpt.get("state_dict"), ckpt.get("meta")
    if not isinstance(state, dict) or not isinstance(meta, dict):
        raise PublishedFileError(f"{path}: not an MMDetection3D checkpoint (it needs state_dict and a meta dict; it "
                           f"holds {_names(sorted(map(str, ckpt)))})")
    version = {k: str(meta[k]) for k in ("mmdet3d_version", "mmengine_version") if k in meta}
    return state, dict(getattr(state, "_metadata", None) or {}), {**version, "epoch": meta.get("epoch"),
                                                                   "classes": _meta_classes(meta)}


def _meta_classes(meta: dict) -> list[str] | None:
    """The file's classes as MMDetection3D's ``init_model`` reads them: ``meta["dataset_meta"]["classes"]``
    (1.x files), else ``meta["CLASSES"]`` (files saved by the mmcv 1.x runner: the published DV-SECOND ones)."""
    dataset_meta = meta.get("dataset_meta")
    classes = dataset_meta.get("classes") if isinstance(dataset_meta, dict) else meta.get("CLASSES")
    return [str(c) for c in classes] if isinstance(classes, (list, tuple)) else None


def map_names(state: dict, source: str, model: str) -> tuple[dict[str, tuple[str, str]], list[str]]:
    """{our name: (reference name, kind)} and the reference names no rule takes."""
    rules = [(re.compile(p), t, s, k) for p, t, s, k in TABLES[(source, model)]]
    mapped, extra = {}, []
    for name in state:
        if name in IGNORED[source]:
            continue
        for pattern, target, shifts, kind in rules:
            m = pattern.fullmatch(name)
            if m:
                groups = {g: str(int(v) + shifts[g]) if g in shifts else v for g, v in m.groupdict().items()}
                mapped[target.format(**groups)] = (name, kind)
                break
        else:
            extra.append(name)
    return mapped, extra


def sparse_weight(t: torch.Tensor, layout: str) -> torch.Tensor:
    """(K, C_in, C_out), z slowest, from a spconv weight in ``layout``."""
    if layout == SPCONV2:
        t = t.permute(1, 2, 3, 4, 0)  # [out, kD, kH, kW, in] -> [kD, kH, kW, in, out]
    return t.reshape(-1, t.shape[-2], t.shape[-1]).contiguous()


def _layouts(t: torch.Tensor, kernel, ours: torch.Size) -> set[str]:
    """The spconv layouts in which ``t`` is the weight of a conv of ``kernel`` with our shape (K, in, out)."""
    _, c_in, c_out = ours
    shapes = {SPCONV1: (*kernel, c_in, c_out), SPCONV2: (c_out, *kernel, c_in)}
    return {layout for layout, shape in shapes.items() if tuple(t.shape) == shape}


def _sparse_layout(path: Path, source: str, sparse: dict, module_meta: dict) -> dict[str, str | None]:
    """{our name: layout} of the sparse convs (None where the shape fits no layout)."""
    if source == "mmdet3d":  # the module's version says it: 2 is spconv 2.x, anything else MMCV's 1.x
        return {ours: (SPCONV2 if (module_meta.get(ref.rsplit(".", 1)[0]) or {}).get("version") == 2 else SPCONV1)
                for ours, (ref, _, _) in sparse.items()}
    fits = [f for f in (_layouts(t, kernel, shape) for _, t, (kernel, shape) in sparse.values()) if f]
    common = set.intersection(*fits) if fits else set()  # (a shape no layout fits is listed by convert)
    if len(common) > 1:
        raise PublishedFileError(f"{path}: every sparse conv's shape fits both {SPCONV1} and {SPCONV2}; the file "
                           "does not say which it holds")
    if fits and not common:
        raise PublishedFileError(f"{path}: its sparse convs mix {SPCONV1} and {SPCONV2}; one file holds one layout")
    return {ours: next(iter(common), None) for ours in sparse}


def convert(path: Path, source: str, model: str, state: dict, module_meta: dict, net,
            config: str) -> dict[str, torch.Tensor]:
    """Our state dict from the reference's, or PublishedFileError listing every missing, extra and misfit
    tensor (``config``: the published config file ``net`` is, for the message)."""
    ours = net.state_dict()
    mapped, extra = map_names(state, source, model)
    missing = sorted(set(ours) - set(mapped))
    extra += sorted(n for n in mapped if n not in ours)
    sparse = {n: (ref, state[ref], (net.get_submodule(n.rsplit(".", 1)[0]).kernel, ours[n].shape))
              for n, (ref, kind) in mapped.items() if kind == SPARSE and n in ours}
    layouts = _sparse_layout(path, source, sparse, module_meta) if sparse else {}
    out, misfit = {}, []
    for name, (ref, kind) in mapped.items():
        if name not in ours:
            continue
        t = state[ref]
        if kind == SPARSE and layouts[name] is not None and _layouts(t, sparse[name][2][0], ours[name].shape):
            t = sparse_weight(t, layouts[name])
        if kind == FC and isinstance(t, torch.Tensor) and t.dim() in (3, 4) and set(t.shape[2:]) == {1}:
            t = t.reshape(t.shape[:2])  # Conv1d / Conv2d of kernel 1, [out, in, 1(, 1)] -> Linear [out, in]
        if not isinstance(t, torch.Tensor) or t.shape != ours[name].shape:
            misfit.append(f"{ref} {tuple(getattr(t, 'shape', ()))} for {name} {tuple(ours[name].shape)}")
            continue
        out[name] = t.to(ours[name].dtype).clone()
    problems = [f"{what} ({len(names)}): {_names(names)}" for what, names in
                (("tensors of ours no reference tensor fills", missing), ("reference tensors with no place", extra),
                 ("shapes that do not fit", misfit)) if names]
    if problems:
        raise PublishedFileError(f"{path}: does not hold the network of {config}: "
                                 + "; ".join(problems))
    return out


def published_network(path: Path, source: str, model: str, classes: list[str] | None):
    """(our ``kitti`` network of the published config whose classes are ``classes``, that config's file);
    ``classes`` None: the main config. Other classes are a PublishedFileError."""
    net = zoo.build(model, "kitti")
    head = net.cfg.head
    if classes is None or classes == list(head.classes):
        return net, CONFIG_FILES[(source, model)]
    config = CLASS_CONFIGS.get((source, model, tuple(classes)))
    if config is None:
        known = [list(head.classes)] + [list(c) for s, m, c in CLASS_CONFIGS if (s, m) == (source, model)]
        raise PublishedFileError(f"{path}: its classes {classes} are not those of a published config of this "
                                 f"network ({' or '.join(map(str, known))})")
    keep = [head.classes.index(c) for c in classes]
    head = dataclasses.replace(head, classes=tuple(classes), sizes=tuple(head.sizes[i] for i in keep),
                               bottoms=tuple(head.bottoms[i] for i in keep))
    return zoo.detector_class(model)(dataclasses.replace(net.cfg, head=head)), config


def import_checkpoint(path, source: str, model: str, out) -> dict:
    """Write our checkpoint of ``model``'s kitti profile from a published file; returns its provenance."""
    path, out = Path(path), Path(out)
    if source not in SOURCES:
        raise ValueError(f"--from: unknown source {source!r}; expected one of {', '.join(SOURCES)}")
    if (source, model) not in TABLES:
        known = ", ".join(f"--from {s} --model {m}" for s, m in TABLES)
        raise ValueError(f"--model {model} --from {source}: no published network is mapped (known: {known})")
    state, module_meta, info = read_published(path, source)
    net, config = published_network(path, source, model, info.get("classes"))
    weights = convert(path, source, model, state, module_meta, net, config)
    provenance = {"source": source, "config": config, "file": path.name,
                  "sha256": sha256_file(path), "classes": list(net.cfg.head.classes),
                  **{k: v for k, v in info.items() if k not in ("classes", "epoch") and v}}
    ckpt = {"model": model, "profile": "kitti", "config": dataclasses.asdict(net.cfg), "state_dict": weights,
            "epoch": info.get("epoch") if isinstance(info.get("epoch"), int) else "", "published": provenance}
    buf = io.BytesIO()
    torch.save(ckpt, buf)
    atomic_write_bytes(out, buf.getvalue())
    return provenance
