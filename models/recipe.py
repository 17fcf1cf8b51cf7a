"""A detector's recipe: how each profile trains it and what starts it, beside its architecture.

- ``Schedule``: the training loop's settings (epochs, batch size, peak learning rate of the one-cycle
  schedule, weight decay, gradient clip) and its levers (weight average, mixed precision). Its fields are
  part of a training's identity (the checkpoint's ``config_hash`` and the run's train-stage key):
  renaming one retrains every model.
- ``PROFILE_SCHEDULES``: the schedule every model of a profile shares unless its recipe says otherwise.
- ``Recipe``: what one model changes of them, and its warm start. Each ``models/<name>.py`` defines
  ``RECIPE = Recipe(...)`` beside its ``CONFIGS``.
- ``ModelRecipe``: one model's recipe resolved for one profile (``models.zoo.resolve``): the network,
  its architecture config, its schedule and its warm start, in one object that training, a run and
  export receive instead of looking the profile up again.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

PROFILES = ("tiny", "compact", "kitti")
AMP_MODES = ("", "bf16")  # Schedule.amp: float32, or autocast to bfloat16 (harness.amp)


@dataclass(frozen=True)
class Schedule:
    epochs: int
    batch_size: int
    lr: float  # peak learning rate of the one-cycle schedule
    weight_decay: float = 0.01
    grad_clip: float = 10.0
    # exponential moving average of the weights (harness.train): the decay per step, 0 = off; a training with it
    # evaluates, checkpoints and exports the averaged copy
    ema: float = 0.0
    # mixed precision of the forward pass and loss (harness.amp): "" float32, "bf16" CPU autocast to bfloat16 where
    # the CPU has native bf16; the weights, optimizer state, checkpoint, validation and export stay float32
    amp: str = ""

    def __post_init__(self):
        if self.amp not in AMP_MODES:
            raise ValueError(f"Schedule: amp {self.amp!r}; expected one of {', '.join(map(repr, AMP_MODES))}")

    def key(self) -> dict:
        """What identifies a training by its schedule: the fields, less those added since that are off (``ema`` 0,
        ``amp`` ""), so that the trainings and runs made before them keep their keys."""
        out = asdict(self)
        for lever in ("ema", "amp"):
            if not out[lever]:
                del out[lever]
        return out


# compact, the default run's profile: each model's RECIPE sets its epochs over the default run's 1,530 training
# frames (batch 2), so that it trains in about 10-80 minutes on one CPU thread beside another job (docs/
# performance.md has each model's measured seconds); the val AP40 3D moderate of held-out frames decided each
# count (the model's RECIPE says what it measured). kitti: OpenPCDet's KITTI schedules.
PROFILE_SCHEDULES = {"tiny": Schedule(epochs=2, batch_size=2, lr=3e-3),
                     "compact": Schedule(epochs=4, batch_size=2, lr=3e-3),
                     "kitti": Schedule(epochs=80, batch_size=4, lr=3e-3)}  # OpenPCDet adam_onecycle


def _check_profiles(where: str, values: dict) -> None:
    unknown = sorted(set(values) - set(PROFILES))
    if unknown:
        raise ValueError(f"Recipe {where}: unknown profile(s) {', '.join(unknown)}; expected {', '.join(PROFILES)}")


@dataclass(frozen=True)
class Recipe:
    """One model's training recipe: where it departs from ``PROFILE_SCHEDULES``, and its warm start."""

    epochs: dict[str, int] = field(default_factory=dict)  # profile -> epochs, where not the profile's
    lr: dict[str, float] = field(default_factory=dict)  # profile -> peak learning rate, where not the profile's
    warm_from: str | None = None  # the sibling model whose checkpoint starts this one's training in a run
    warm_lr: float | None = None  # peak learning rate of a warm-started training, where it differs
    # (prefix in this model, prefix in the sibling's checkpoint) where it keeps the sibling's weights by another name
    warm_aliases: tuple[tuple[str, str], ...] = ()

    def __post_init__(self):
        _check_profiles("epochs", self.epochs)
        _check_profiles("lr", self.lr)
        if self.warm_lr is not None and self.warm_from is None:
            raise ValueError("Recipe: warm_lr without warm_from (a run starts the model from nothing)")

    def schedule(self, profile: str, warm: bool = False) -> Schedule:
        """The schedule of ``profile``; ``warm``: the training starts from a checkpoint (``warm_lr``)."""
        if profile not in PROFILE_SCHEDULES:
            raise ValueError(f"unknown profile {profile!r}; expected one of {', '.join(PROFILE_SCHEDULES)}")
        base = PROFILE_SCHEDULES[profile]
        lr = self.warm_lr if warm and self.warm_lr is not None else self.lr.get(profile, base.lr)
        return replace(base, epochs=self.epochs.get(profile, base.epochs), lr=lr)


@dataclass(frozen=True)
class ModelRecipe:
    """One model in one profile, resolved once: what trains, runs and exports it."""

    model: str  # the model name (command line, file names)
    profile: str  # the model profile: tiny | compact | kitti
    config: object  # the profile's architecture config (``CONFIGS[profile]`` of models/<model>.py)
    schedule: Schedule  # the training schedule (warm-start learning rate applied when warm)
    network: type  # the Detector class; ``build()`` makes it from ``config``
    warm_from: str | None = None  # the sibling whose checkpoint starts the training (None: from nothing)
    warm_aliases: tuple[tuple[str, str], ...] = ()  # see ``Recipe.warm_aliases``

    def build(self):
        """A freshly initialised detector (from the global torch generator)."""
        return self.network(self.config)
