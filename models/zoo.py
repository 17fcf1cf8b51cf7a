"""Model registry by name and checkpoint loading.

- ``MODEL_NAMES``: the seven detector names (README).
- ``build(name, profile="compact") -> Detector``: imports ``models.<name>`` lazily; every
  detector module exposes ``CONFIGS: dict[str, Config]`` with keys "tiny", "compact", "kitti",
  ``RECIPE: Recipe`` and ``build(profile) -> Detector``.
- ``recipe(name) -> Recipe``: the model's training recipe (``RECIPE`` of models/<name>.py).
- ``resolve(name, profile, warm) -> ModelRecipe``: the model in one profile, resolved once: its
  network, architecture config, training schedule and warm start (``models.recipe``).
- ``available()``: names whose module imports.
- ``read_checkpoint(path) -> dict``: a checkpoint's contents, loaded with ``weights_only=True``
  (tensors and plain Python data only: a pickle that would run code is refused, never run).
- ``load_checkpoint(path) -> (Detector, meta)``: rebuilds the model of a checkpoint written by
  ``harness.train.train`` (keys: model, profile, config, state_dict, epoch, optimizer,
  data_hash, config_hash) and loads its weights; ``meta`` is the checkpoint without the
  state dicts. The model is built from the config the checkpoint was trained with, not from the
  profile's config of the code that loads it: a config changed since (a point count, an NMS
  threshold) would otherwise run the weights in a network they were not trained in, and many
  such changes leave every weight's shape alone. ``meta["config_changed"]`` lists the fields
  where the two differ.
"""
from __future__ import annotations

import dataclasses
import hashlib
import importlib
import pickle
import re
import zipfile
from pathlib import Path

import torch

from models.base import Detector
from models.recipe import PROFILES, ModelRecipe, Recipe  # noqa: F401 - PROFILES: re-exported (zoo.PROFILES)

MODEL_NAMES = ("pointpillars", "second", "dv_second", "parta2", "pv_rcnn", "point_rcnn", "mvx_net")

class CheckpointError(ValueError):
    """A checkpoint file that cannot be loaded (message names the file and the problem)."""


def _module(name: str):
    if name not in MODEL_NAMES:
        raise ValueError(f"unknown model {name!r}; expected one of {', '.join(MODEL_NAMES)}")
    return importlib.import_module(f"models.{name}")


def config(name: str, profile: str = "compact"):
    """The frozen config dataclass of a model profile."""
    module = _module(name)
    if profile not in module.CONFIGS:
        raise ValueError(f"unknown profile {profile!r} for model {name!r}; "
                         f"expected one of {', '.join(module.CONFIGS)}")
    return module.CONFIGS[profile]


def build(name: str, profile: str = "compact") -> Detector:
    """A freshly initialised detector."""
    config(name, profile)  # validates name and profile with a clear message
    return _module(name).build(profile)


def recipe(name: str) -> Recipe:
    """The training recipe of a model (its module's ``RECIPE``)."""
    return _module(name).RECIPE


def resolve(name: str, profile: str = "compact", warm: bool = False) -> ModelRecipe:
    """``name`` in ``profile``, resolved once; ``warm``: its training starts from a checkpoint (in a
    run, its recipe's ``warm_from`` sibling's; the schedule then takes the recipe's ``warm_lr``)."""
    rec = recipe(name)
    return ModelRecipe(model=name, profile=profile, config=config(name, profile), schedule=rec.schedule(profile, warm),
                       network=detector_class(name), warm_from=rec.warm_from if warm else None,
                       warm_aliases=rec.warm_aliases)


def available() -> tuple[str, ...]:
    """Model names whose module imports (others may still be under construction)."""
    names = []
    for name in MODEL_NAMES:
        try:
            _module(name)
        except ImportError:
            continue
        names.append(name)
    return tuple(names)


def count_parameters(model: torch.nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def read_checkpoint(path, map_location="cpu") -> dict:
    """The contents of a checkpoint file: tensors and plain Python data (what ``harness.train``
    stores), loaded with ``torch.load(weights_only=True)``. A file that holds anything else (a
    pickle that would call a function, say) is refused without running any of it."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    with path.open("rb") as f:
        first = f.read(1)
    if not zipfile.is_zipfile(path) and first != b"\x80":  # torch.save: a zip archive, or a legacy pickle
        raise CheckpointError(f"{path}: not a checkpoint (neither the zip archive torch.save writes nor a pickle)")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        found = re.search(r"GLOBAL (\S+)", str(exc)) or re.search(r"Unsupported [^\n]{1,80}", str(exc))
        why = ("it refers to " + found.group(1) if found.groups() else found.group(0)) if found else "an unknown pickle"
        raise CheckpointError(f"{path}: refused: it holds more than tensors and plain data ({why}), so loading it "
                              "could run code") from None
    except Exception as exc:  # noqa: BLE001 - torch raises many types for a corrupt file
        raise CheckpointError(f"{path}: not a readable checkpoint ({str(exc).splitlines()[0][:200]})") from None
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{path}: not a checkpoint (holds a {type(ckpt).__name__}, not the dict of tensors "
                              "and data a checkpoint holds)")
    return ckpt


def config_from_dict(base, saved: dict, where: str = ""):
    """The config dataclass ``base`` with the values of ``saved`` (``dataclasses.asdict`` of a
    config of the same class; nested configs field by field). A field ``saved`` lacks keeps the
    base's value; a field ``base`` lacks is a ValueError naming it."""
    if not isinstance(saved, dict):
        raise ValueError(f"{where or 'config'}: a {type(saved).__name__}, not a mapping of fields")
    names = {f.name for f in dataclasses.fields(base)}
    unknown = sorted(set(saved) - names)
    if unknown:
        raise ValueError(f"fields this code's {type(base).__name__} does not have: "
                         + ", ".join(f"{where}{k}" for k in unknown))
    return dataclasses.replace(base, **{n: _rebuilt(getattr(base, n), saved[n], f"{where}{n}") for n in names & set(saved)})


def _rebuilt(old, new, where: str):
    """A saved value ``new`` in the type of the config's value ``old``: a nested config from its
    dict, a tuple (of configs: each from the template at its place, or the first) from a sequence."""
    if dataclasses.is_dataclass(old):
        return config_from_dict(old, new, where + ".")
    if isinstance(old, tuple) and isinstance(new, (tuple, list)):
        if not old:
            return tuple(new)
        return tuple(_rebuilt(old[min(i, len(old) - 1)], v, f"{where}[{i}]") for i, v in enumerate(new))
    return new


def config_changes(a, b, where: str = "") -> list[str]:
    """Dotted names of the fields where the config dataclasses a and b differ."""
    out = []
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if dataclasses.is_dataclass(x) and dataclasses.is_dataclass(y):
            out += config_changes(x, y, f"{where}{f.name}.")
        elif x != y:
            out.append(f"{where}{f.name}")
    return out


def detector_class(name: str) -> type:
    """The detector class of a model name (the Detector subclass whose ``architecture`` it is)."""
    module = _module(name)
    return next(c for c in vars(module).values() if isinstance(c, type) and issubclass(c, Detector)
                and c.__dict__.get("architecture") == name)


def _refuse_broken_weights(path: Path, state_dict) -> None:
    """A checkpoint whose weights hold NaN or inf (a diverged training) or a negative BatchNorm
    variance is refused: every box of such a network is NaN, or none is made."""
    if not isinstance(state_dict, dict):
        raise CheckpointError(f"{path}: state_dict is a {type(state_dict).__name__}, not a mapping of tensors")
    bad = [n for n, t in state_dict.items()
           if isinstance(t, torch.Tensor) and t.is_floating_point() and not torch.isfinite(t).all()]
    if bad:
        raise CheckpointError(f"{path}: {len(bad)} of its {len(state_dict)} tensors hold NaN or inf (first: {bad[0]}); "
                              "the training that wrote it diverged")
    negative = [n for n, t in state_dict.items() if n.endswith("running_var") and isinstance(t, torch.Tensor)
                and (t < 0).any()]
    if negative:  # its square root is NaN at inference: every box of the network vanishes
        raise CheckpointError(f"{path}: the BatchNorm variance {negative[0]} holds negative values; no training "
                              "writes that")


def load_checkpoint(path) -> tuple[Detector, dict]:
    """(model in eval mode, metadata) from a checkpoint file, built with the config it was
    trained with (module docstring)."""
    path = Path(path)
    ckpt = read_checkpoint(path)
    missing = {"model", "profile", "state_dict"} - set(ckpt)
    if missing:
        raise CheckpointError(f"{path}: checkpoint lacks {', '.join(sorted(missing))}")
    try:
        current = config(ckpt["model"], ckpt["profile"])
    except ValueError as exc:
        raise CheckpointError(f"{path}: {exc}") from None
    trained = current
    if "config" in ckpt:
        try:
            trained = config_from_dict(current, ckpt["config"])
        except (ValueError, TypeError) as exc:
            raise CheckpointError(f"{path}: its {ckpt['model']}/{ckpt['profile']} config does not fit this "
                                  f"code ({exc}); it was trained by another version") from None
    changed = config_changes(current, trained)
    try:
        model = detector_class(ckpt["model"])(trained)
    except (ValueError, TypeError, RuntimeError, ZeroDivisionError) as exc:  # a config no training writes
        raise CheckpointError(f"{path}: its {ckpt['model']}/{ckpt['profile']} config does not build the network "
                              f"({str(exc).splitlines()[0][:200]})") from None
    _refuse_broken_weights(path, ckpt["state_dict"])
    try:
        model.load_state_dict(ckpt["state_dict"])
    except RuntimeError as exc:
        raise CheckpointError(f"{path}: weights do not fit {ckpt['model']}/{ckpt['profile']}: "
                              f"{exc}") from exc
    model.eval()
    meta = {k: v for k, v in ckpt.items() if k not in ("state_dict", "optimizer")}
    if changed:
        meta["config_changed"] = changed
    return model, meta


def weights_digest(state_dict: dict) -> str:
    """SHA-256 (16 hex) of a state dict's tensors (names, dtypes, shapes, values): the identity of
    trained weights, which the checkpoint file's bytes are not (they also hold the training time)."""
    h = hashlib.sha256()
    for name in sorted(state_dict):
        t = state_dict[name].detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()[:16]


def warm_start(net: torch.nn.Module, model: str | ModelRecipe, path) -> tuple[list[str], list[str]]:
    """Load into ``net`` (a ``model``: its name or its ModelRecipe) every tensor of the checkpoint at
    ``path`` whose name (after the recipe's ``warm_aliases``) and shape match one of ``net``'s: a first
    stage trained as its one-stage sibling (PV-RCNN's or Part-A2's from SECOND, MVX-Net's LiDAR network
    from DV-SECOND), the rest as initialised. Returns (loaded names, names left as they were). A
    checkpoint from which nothing fits is refused."""
    path = Path(path)
    ckpt = read_checkpoint(path)
    if "state_dict" not in ckpt:
        raise CheckpointError(f"{path}: checkpoint lacks state_dict")
    source = ckpt["state_dict"]
    _refuse_broken_weights(path, source)
    aliases = (model if isinstance(model, ModelRecipe) else recipe(model)).warm_aliases
    model = model.model if isinstance(model, ModelRecipe) else model
    own = net.state_dict()
    take, loaded, kept = {}, [], []
    for name, tensor in own.items():
        candidates = [name] + [src + name[len(dst):] for dst, src in aliases
                               if name.startswith(dst)]
        hit = next((c for c in candidates if c in source and source[c].shape == tensor.shape), None)
        if hit is None:
            kept.append(name)
        else:
            take[name] = source[hit]
            loaded.append(name)
    if not any(own[n].is_floating_point() for n in loaded):
        raise CheckpointError(f"{path}: no weights of this {ckpt.get('model', 'unknown')!r} checkpoint fit {model!r}")
    net.load_state_dict(take, strict=False)
    return loaded, kept
