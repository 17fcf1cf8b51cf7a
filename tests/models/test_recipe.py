"""Every model's training recipe, pinned: the numbers each profile trains with (epochs, batch size,
peak learning rate, weight decay, gradient clip), cold and warm-started, the sibling a run starts it
from and the run profiles' model profiles. Moving a recipe must not change one of them."""
import pytest

from models import zoo
from models.zoo import MODEL_NAMES

# (epochs, batch_size, lr, weight_decay, grad_clip) per model and profile, cold start
COLD = {
    "pointpillars": {"tiny": (2, 2, 3e-3, 0.01, 10.0), "compact": (5, 2, 3e-3, 0.01, 10.0), "kitti": (80, 4, 3e-3, 0.01, 10.0)},
    "second": {"tiny": (2, 2, 3e-3, 0.01, 10.0), "compact": (2, 2, 3e-3, 0.01, 10.0), "kitti": (80, 4, 3e-3, 0.01, 10.0)},
    "dv_second": {"tiny": (2, 2, 3e-3, 0.01, 10.0), "compact": (2, 2, 3e-3, 0.01, 10.0), "kitti": (80, 4, 3e-3, 0.01, 10.0)},
    "parta2": {"tiny": (2, 2, 3e-3, 0.01, 10.0), "compact": (1, 2, 3e-3, 0.01, 10.0), "kitti": (80, 4, 0.01, 0.01, 10.0)},
    "pv_rcnn": {"tiny": (2, 2, 3e-3, 0.01, 10.0), "compact": (1, 2, 3e-3, 0.01, 10.0), "kitti": (80, 4, 0.01, 0.01, 10.0)},
    "point_rcnn": {"tiny": (2, 2, 3e-3, 0.01, 10.0), "compact": (4, 2, 3e-3, 0.01, 10.0), "kitti": (80, 4, 0.01, 0.01, 10.0)},
    "mvx_net": {"tiny": (2, 2, 3e-3, 0.01, 10.0), "compact": (1, 2, 3e-3, 0.01, 10.0), "kitti": (80, 4, 3e-3, 0.01, 10.0)},
}
WARM_LR = {"mvx_net": 1e-3}  # the peak learning rate of a warm-started training, where it differs
WARM_FROM = {"pv_rcnn": "second", "parta2": "second", "mvx_net": "dv_second"}
WARM_ALIASES = {"pv_rcnn": (("rpn.", "head."),), "parta2": (("rpn.", "head."), ("unet.encoder.", "backbone3d."))}
RUN_PROFILES = {"quick": "tiny", "default": "compact", "full": "kitti"}


def schedule(name: str, profile: str, warm: bool) -> tuple:
    s = zoo.resolve(name, profile, warm=warm).schedule
    return (s.epochs, s.batch_size, s.lr, s.weight_decay, s.grad_clip)


def warm_from(name: str):
    assert zoo.resolve(name, "tiny", warm=False).warm_from is None  # a cold start has no sibling
    return zoo.resolve(name, "tiny", warm=True).warm_from


def warm_aliases(name: str) -> tuple:
    return zoo.recipe(name).warm_aliases


def test_every_model_has_a_pinned_recipe():
    assert set(COLD) == set(MODEL_NAMES)


@pytest.mark.parametrize("name", MODEL_NAMES)
@pytest.mark.parametrize("profile", ("tiny", "compact", "kitti"))
def test_schedule_is_pinned(name, profile):
    cold = COLD[name][profile]
    assert schedule(name, profile, warm=False) == cold
    warm = cold[:2] + (WARM_LR.get(name, cold[2]),) + cold[3:]
    assert schedule(name, profile, warm=True) == warm


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_warm_start_is_pinned(name):
    assert warm_from(name) == WARM_FROM.get(name)
    assert warm_aliases(name) == WARM_ALIASES.get(name, ())


def test_run_profiles_map_to_model_profiles():
    from harness.run import PROFILES
    assert {k: v.model_profile for k, v in PROFILES.items()} == RUN_PROFILES


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_a_resolved_recipe_holds_the_profiles_network_and_config(name):
    import torch
    r = zoo.resolve(name, "tiny")
    assert r.config == zoo.config(name, "tiny") and r.network is zoo.detector_class(name)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(3)
        a = r.build().state_dict()
        torch.manual_seed(3)
        b = zoo.build(name, "tiny").state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_recipe_errors_are_clear():
    with pytest.raises(ValueError, match="unknown profile 'huge'"):
        zoo.resolve("second", "huge")
    with pytest.raises(ValueError, match="unknown profile"):
        zoo.Recipe(epochs={"fast": 3})
    with pytest.raises(ValueError, match="warm_lr without warm_from"):
        zoo.Recipe(warm_lr=1e-3)


def test_a_schedule_key_leaves_out_the_levers_that_are_off():
    """A training keyed before ``ema`` existed keeps its key while the average is off; with it on, the key differs."""
    from dataclasses import replace

    from models.recipe import Schedule
    s = Schedule(epochs=4, batch_size=2, lr=3e-3)
    assert s.key() == {"epochs": 4, "batch_size": 2, "lr": 3e-3, "weight_decay": 0.01, "grad_clip": 10.0}
    assert replace(s, ema=0.999).key() == {**s.key(), "ema": 0.999}


def test_a_schedule_key_leaves_out_amp_while_off():
    """Mixed precision off (amp ""), the key is the one before it existed; on, the key names it; an unknown mode
    is refused."""
    from dataclasses import replace

    from models.recipe import Schedule
    s = Schedule(epochs=4, batch_size=2, lr=3e-3)
    assert "amp" not in s.key() and "amp" not in replace(s, ema=0.999).key()
    assert replace(s, amp="bf16").key() == {**s.key(), "amp": "bf16"}
    with pytest.raises(ValueError, match="amp 'fp16'"):
        replace(s, amp="fp16")
