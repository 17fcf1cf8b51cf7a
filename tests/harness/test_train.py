import hashlib

import numpy as np
import pytest
import torch

from harness.amp import native_bf16
from harness.augment import AugmentConfig
from harness.dataset import write_synthetic_dataset
from harness.gt_database import GtSamplingConfig
from harness.train import train
from models import zoo


def test_train_writes_checkpoint_and_resumes(tmp_path, capsys):
    data = write_synthetic_dataset(tmp_path / "data", frames=5, seed=0, val=1)
    epochs = []  # the run's progress callback: epochs done, epochs, mean seconds per epoch
    ckpt = train("pointpillars", data, tmp_path / "run", profile="tiny", epochs=2, seed=0, progress=True,
                 on_epoch=lambda done, total, seconds: epochs.append((done, total, seconds > 0)))
    assert epochs == [(1, 2, True), (2, 2, True)]
    state = torch.load(ckpt, weights_only=False)
    assert state["model"] == "pointpillars" and state["epoch"] == 2 and state["profile"] == "tiny"
    assert state["config"]["pfn_channels"] == zoo.config("pointpillars", "tiny").pfn_channels
    assert len(state["data_hash"]) == 16 and len(state["config_hash"]) == 16 and "optimizer" in state
    assert np.isfinite(state["final_loss"])
    out = capsys.readouterr()
    assert "val AP40" in out.out
    history = state["val_history"]  # the convergence check: one entry per epoch
    assert [h["epoch"] for h in history] == [1, 2] and history[-1]["loss"] == state["final_loss"]
    assert all(h["frames"] == 1 and 0 <= h["3d_moderate"] <= 100 for h in history)
    assert "epoch 2/2: loss" in out.out and "val AP40 3D moderate after each epoch" in out.out
    mtime = ckpt.stat().st_mtime_ns
    train("pointpillars", data, tmp_path / "run", profile="tiny", epochs=2, seed=0, progress=False)
    assert ckpt.stat().st_mtime_ns == mtime  # complete: resumed, nothing retrained
    train("pointpillars", data, tmp_path / "run", profile="tiny", seed=0, progress=False)
    assert ckpt.stat().st_mtime_ns == mtime  # the profile's 2 epochs: the same training
    model, meta = zoo.load_checkpoint(ckpt)
    assert meta["epoch"] == 2
    again = train("pointpillars", data, tmp_path / "other", profile="tiny", epochs=2, seed=0, progress=False)
    for k, v in torch.load(again, weights_only=False)["state_dict"].items():
        assert torch.allclose(v.float(), state["state_dict"][k].float(), atol=1e-5)  # same seed, same run


def test_a_training_whose_loss_turns_nan_stops_naming_the_step_and_keeps_the_last_epoch(tmp_path, monkeypatch):
    from models.pointpillars import PointPillars
    data = write_synthetic_dataset(tmp_path / "data", frames=4, seed=5)
    train_stopped_after_epoch_1(monkeypatch, "pointpillars", data, tmp_path / "run", profile="tiny", seed=0,
                                progress=False)
    ckpt = tmp_path / "run" / "checkpoint.pt"
    before = torch.load(ckpt, weights_only=False)
    loss = PointPillars.loss
    monkeypatch.setattr(PointPillars, "loss", lambda self, samples: {"loss": loss(self, samples)["loss"] * float("nan")})
    with pytest.raises(ValueError, match=r"data: the training loss is nan at epoch 2, step 1 \(frames \d{6}, \d{6}\)"):
        train("pointpillars", data, tmp_path / "run", profile="tiny", seed=0, progress=False)
    after = torch.load(ckpt, weights_only=False)
    assert after["epoch"] == 1 and all(torch.equal(after["state_dict"][k], v) for k, v in before["state_dict"].items())


def train_stopped_after_epoch_1(monkeypatch, *args, **kwargs) -> None:
    """``train(*args, **kwargs)`` interrupted as its second epoch begins (its checkpoint holds epoch 1)."""
    import harness.train as train_mod
    run_epoch = train_mod._run_epoch

    def stop_at_epoch_1(*a, **k):
        if a[6] == 1:  # (net, ds, optimizer, scheduler, tcfg, seed, epoch, ...)
            raise KeyboardInterrupt
        return run_epoch(*a, **k)

    monkeypatch.setattr(train_mod, "_run_epoch", stop_at_epoch_1)
    with pytest.raises(KeyboardInterrupt):
        train(*args, **kwargs)
    monkeypatch.setattr(train_mod, "_run_epoch", run_epoch)


def test_a_training_stopped_before_its_validation_validates_when_run_again(tmp_path):
    data = write_synthetic_dataset(tmp_path / "data", frames=4, seed=6, val=1)
    ckpt = train("pointpillars", data, tmp_path / "run", profile="tiny", epochs=1, progress=False)
    state = torch.load(ckpt, weights_only=False)
    expected = state.pop("val_ap")
    torch.save(state, ckpt)  # the last epoch's checkpoint, written just before a stop
    train("pointpillars", data, tmp_path / "run", profile="tiny", epochs=1, progress=False)
    again = torch.load(ckpt, weights_only=False)
    assert again["val_ap"] == expected and again["epoch"] == 1


def test_a_resumed_training_keeps_its_val_history(tmp_path, monkeypatch):
    data = write_synthetic_dataset(tmp_path / "data", frames=4, seed=7, val=1)
    train_stopped_after_epoch_1(monkeypatch, "pointpillars", data, tmp_path / "run", profile="tiny", seed=0,
                                progress=False)
    ckpt = tmp_path / "run" / "checkpoint.pt"
    first = torch.load(ckpt, weights_only=False)["val_history"]
    assert [h["epoch"] for h in first] == [1]
    train("pointpillars", data, tmp_path / "run", profile="tiny", seed=0, progress=False)
    history = torch.load(ckpt, weights_only=False)["val_history"]
    assert [h["epoch"] for h in history] == [1, 2] and history[0] == first[0]


def test_resumed_training_sums_its_seconds(tmp_path, monkeypatch):
    """A run stopped after epoch 1 and resumed reports the time of both sessions."""
    data = write_synthetic_dataset(tmp_path / "data", frames=4, seed=1)
    train_stopped_after_epoch_1(monkeypatch, "pointpillars", data, tmp_path / "run", profile="tiny", seed=0,
                                progress=False)
    ckpt = tmp_path / "run" / "checkpoint.pt"
    state = torch.load(ckpt, weights_only=False)
    assert state["epoch"] == 1
    torch.save({**state, "train_seconds": 1000.0}, ckpt)  # a long first session
    train("pointpillars", data, tmp_path / "run", profile="tiny", seed=0, progress=False)
    resumed = torch.load(ckpt, weights_only=False)
    assert resumed["epoch"] == 2 and 1000.0 < resumed["train_seconds"] < 1000.0 + 60


def test_two_stage_training_is_repeatable_whatever_the_global_rng(tmp_path):
    """Part-A2's RoI head has dropout: two trainings with the same seed give the same weights,
    whatever state torch's global generator was in before."""
    data = write_synthetic_dataset(tmp_path / "data", frames=4, seed=2)
    states = []
    for i in range(2):
        torch.manual_seed(1000 + i)
        ckpt = train("parta2", data, tmp_path / f"run{i}", profile="tiny", epochs=1, seed=0, progress=False)
        states.append(torch.load(ckpt, weights_only=False)["state_dict"])
    assert torch.initial_seed() == 1001  # the caller's generator is left alone
    for k, v in states[0].items():
        assert torch.equal(v, states[1][k]), k


@pytest.mark.parametrize("model", ["parta2", "point_rcnn"])
def test_resumed_two_stage_training_equals_an_uninterrupted_one(tmp_path, monkeypatch, model):
    """RoI sampling draws from the model's own generator: a training stopped after epoch 1 and
    resumed ends with the weights of one that ran through."""
    data = write_synthetic_dataset(tmp_path / "data", frames=4, seed=3)
    whole = train(model, data, tmp_path / "whole", profile="tiny", epochs=2, seed=0, progress=False)
    train_stopped_after_epoch_1(monkeypatch, model, data, tmp_path / "parts", profile="tiny", epochs=2, seed=0,
                                progress=False)
    parts = train(model, data, tmp_path / "parts", profile="tiny", epochs=2, seed=0, progress=False)
    a, b = (torch.load(p, weights_only=False)["state_dict"] for p in (whole, parts))
    for k, v in a.items():
        assert torch.equal(v, b[k]), k


NO_AUGMENTATION = AugmentConfig(flip_y=False, rotation=0.0, scale=(1.0, 1.0),
                                gt_sampling=GtSamplingConfig(enabled=False))


def test_data_parallel_training_takes_the_single_process_steps(tmp_path, monkeypatch):
    """Two workers, each with one frame of every batch (5 frames: the last batch leaves one worker
    without a frame), end with the weights of one process that ran both frames of each batch; and
    so does a one-process training stopped after epoch 1 and resumed by two workers."""
    data = write_synthetic_dataset(tmp_path / "data", frames=6, seed=4, val=1)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as each worker on a 2-core machine
    try:
        one = train("pointpillars", data, tmp_path / "one", profile="tiny", epochs=2, progress=False,
                    aug=NO_AUGMENTATION)
    finally:
        torch.set_num_threads(threads)
    two = train("pointpillars", data, tmp_path / "two", profile="tiny", epochs=2, progress=False,
                aug=NO_AUGMENTATION, workers=2)
    a, b = (torch.load(p, weights_only=False) for p in (one, two))
    assert b["workers"] == 2 and b["epoch"] == 2 and "val_ap" in b
    assert b["final_loss"] == pytest.approx(a["final_loss"], rel=1e-5)
    params = dict(zoo.build("pointpillars", "tiny").named_parameters())
    for k, v in a["state_dict"].items():
        if k in params:
            assert torch.allclose(v, b["state_dict"][k], rtol=1e-5, atol=1e-6), k
        elif k.endswith("num_batches_tracked"):
            assert torch.equal(v, b["state_dict"][k]), k  # every frame's forward counted once
        else:  # running statistics: the workers' mean, not one sequence of updates
            assert torch.isfinite(b["state_dict"][k]).all(), k
    mtime = two.stat().st_mtime_ns
    train("pointpillars", data, tmp_path / "two", profile="tiny", epochs=2, progress=False,
          aug=NO_AUGMENTATION, workers=2)
    assert two.stat().st_mtime_ns == mtime  # complete: nothing retrained, no worker started

    torch.set_num_threads(1)
    try:
        train_stopped_after_epoch_1(monkeypatch, "pointpillars", data, tmp_path / "resumed", profile="tiny",
                                    epochs=2, progress=False, aug=NO_AUGMENTATION)
    finally:
        torch.set_num_threads(threads)
    ckpt = tmp_path / "resumed" / "checkpoint.pt"
    state = torch.load(ckpt, weights_only=False)
    torch.save({**state, "train_seconds": 1000.0}, ckpt)  # marks the first session's checkpoint
    resumed = train("pointpillars", data, tmp_path / "resumed", profile="tiny", epochs=2, progress=False,
                    aug=NO_AUGMENTATION, workers=2)
    c = torch.load(resumed, weights_only=False)
    assert c["epoch"] == 2 and c["train_seconds"] > 1000  # resumed: the first session's seconds count
    assert c["final_loss"] == pytest.approx(b["final_loss"], rel=1e-5)
    for k in params:
        assert torch.allclose(c["state_dict"][k], b["state_dict"][k], rtol=1e-5, atol=1e-6), k


def test_a_data_parallel_worker_reports_a_bad_frame(tmp_path):
    data = write_synthetic_dataset(tmp_path / "data", frames=4, seed=5)
    bad = sorted((data / "training" / "velodyne").glob("*.bin"))[1]
    bad.write_bytes(b"\0" * 10)  # not a whole number of (x, y, z, intensity) float32 points
    with pytest.raises(ValueError, match=bad.name):
        train("pointpillars", data, tmp_path / "run", profile="tiny", epochs=1, progress=False,
              aug=NO_AUGMENTATION, workers=2)
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


_NO_CUDA = pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")


@pytest.mark.parametrize("flags, message", [
    (["--workers", "3"], "workers must be between 1 and the batch size 2, got 3"),
    (["--ema", "1.5"], "--ema 1.5: the average's decay per step lies in [0, 1)"),
    pytest.param(["--device", "cuda"], "sees no CUDA device here; train with --device cpu", marks=_NO_CUDA),
])
def test_train_refuses_bad_arguments_before_any_work(tmp_path, capsys, flags, message):
    from harness.cli import main
    data = write_synthetic_dataset(tmp_path / "data", frames=2, seed=6)
    assert main(["--quiet", "train", "--model", "pointpillars", "--profile", "tiny", "--data", str(data),
                 "--out", str(tmp_path / "run"), *flags]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_a_torchrun_launch_trains_as_the_spawned_workers(tmp_path):
    """`sotif-bench train` under torchrun (two local processes, env:// rendezvous, gloo) takes the
    steps of `--workers 2`: same frames per worker, same draws, same all-reduce."""
    import os
    import subprocess
    import sys
    data = write_synthetic_dataset(tmp_path / "data", frames=5, seed=5, val=1)
    spawned = train("pointpillars", data, tmp_path / "spawned", profile="tiny", epochs=1, progress=False, workers=2)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", "-m", "harness.cli",
           "train", "--model", "pointpillars", "--data", str(data), "--out", str(tmp_path / "launched"),
           "--profile", "tiny", "--epochs", "1", "--workers", "1", "--quiet"]  # one process each: workers 2 only if launched
    done = subprocess.run(cmd, env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    a, b = (torch.load(p, weights_only=False) for p in (spawned, tmp_path / "launched" / "checkpoint.pt"))
    assert b["workers"] == 2 and b["epoch"] == 1 and "val_ap" in b
    assert b["final_loss"] == pytest.approx(a["final_loss"], rel=1e-5)
    for k, v in a["state_dict"].items():
        assert torch.allclose(v.float(), b["state_dict"][k].float(), rtol=1e-5, atol=1e-6), k


@pytest.mark.parametrize("model,sibling,aliases", [("pv_rcnn", "second", {"rpn.": "head."}),
                                                   ("parta2", "second", {"rpn.": "head.", "unet.encoder.": "backbone3d."}),
                                                   ("mvx_net", "dv_second", {})])
def test_warm_start_takes_the_siblings_first_stage(tmp_path, model, sibling, aliases):
    torch.manual_seed(0)
    src = zoo.build(sibling, "tiny")
    torch.save({"model": sibling, "state_dict": src.state_dict()}, tmp_path / "sibling.pt")
    torch.manual_seed(1)
    net = zoo.build(model, "tiny")
    before = {k: v.clone() for k, v in net.state_dict().items()}
    loaded, kept = zoo.warm_start(net, model, tmp_path / "sibling.pt")
    source = src.state_dict()
    for name, tensor in net.state_dict().items():  # brute force: the sibling's tensor under the renamed name
        renamed = next((src_p + name[len(p):] for p, src_p in aliases.items() if name.startswith(p)), name)
        fits = renamed in source and source[renamed].shape == tensor.shape
        assert (name in loaded) == fits and (name in kept) == (not fits), name
        assert torch.equal(tensor, source[renamed] if fits else before[name]), name
    assert any(n.startswith(("backbone2d.", "rpn.", "head.")) for n in loaded)
    assert any(n.startswith(("rcnn.", "refine.", "image_branch.")) for n in kept)  # the parts the sibling lacks


def test_warm_start_refuses_a_checkpoint_that_does_not_fit(tmp_path):
    torch.save({"model": "second", "state_dict": zoo.build("second", "tiny").state_dict()}, tmp_path / "s.pt")
    with pytest.raises(zoo.CheckpointError, match=r"s\.pt: no weights of this 'second' checkpoint fit 'point_rcnn'"):
        zoo.warm_start(zoo.build("point_rcnn", "tiny"), "point_rcnn", tmp_path / "s.pt")


def test_train_init_from_a_sibling_is_its_own_training(tmp_path, capsys):
    from harness.cli import main
    data = write_synthetic_dataset(tmp_path / "data", frames=3, seed=0)
    second = train("second", data, tmp_path / "second", profile="tiny", epochs=1, seed=0, progress=False)
    args = ["train", "--model", "pv_rcnn", "--data", str(data), "--profile", "tiny", "--epochs", "1", "--quiet",
            "--workers", "1"]
    assert main(args + ["--out", str(tmp_path / "warm"), "--init-from", str(second)]) == 0
    assert main(args + ["--out", str(tmp_path / "cold")]) == 0
    warm = torch.load(tmp_path / "warm" / "checkpoint.pt", weights_only=False)
    cold = torch.load(tmp_path / "cold" / "checkpoint.pt", weights_only=False)
    assert warm["config_hash"] != cold["config_hash"]  # a warm start (and a changed sibling) is another training
    # the warm start changed where training began: the first-stage weights differ from the cold run's
    assert not torch.equal(warm["state_dict"]["rpn.conv_cls.weight"], cold["state_dict"]["rpn.conv_cls.weight"])
    mtime = (tmp_path / "warm" / "checkpoint.pt").stat().st_mtime_ns
    assert main(args + ["--out", str(tmp_path / "warm"), "--init-from", str(second)]) == 0  # resumed: complete
    assert (tmp_path / "warm" / "checkpoint.pt").stat().st_mtime_ns == mtime
    capsys.readouterr()
    assert main(args + ["--out", str(tmp_path / "x"), "--init-from", str(tmp_path / "missing.pt")]) == 2
    assert "missing.pt: checkpoint not found" in capsys.readouterr().err
    # the same sibling weights in another file (another training time, as on a rerun): the same training
    ckpt = torch.load(second, weights_only=True)
    ckpt["train_seconds"] = ckpt["train_seconds"] + 123.0
    torch.save(ckpt, tmp_path / "second_again.pt")
    assert main(args + ["--out", str(tmp_path / "again"), "--init-from", str(tmp_path / "second_again.pt")]) == 0
    again = torch.load(tmp_path / "again" / "checkpoint.pt", weights_only=True)
    assert again["config_hash"] == warm["config_hash"]
    assert all(torch.equal(again["state_dict"][k], warm["state_dict"][k]) for k in warm["state_dict"])


def test_weights_digest_against_hashlib_over_the_raw_bytes():
    rng = np.random.default_rng(0)
    sd = {"b": torch.from_numpy(rng.normal(size=(3, 4)).astype(np.float32)), "a": torch.arange(5),
          "empty": torch.zeros(0, 2), "n": torch.tensor(7)}
    h = hashlib.sha256()
    for name in ("a", "b", "empty", "n"):
        t = sd[name]
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode() + t.numpy().tobytes())
    assert zoo.weights_digest(sd) == h.hexdigest()[:16]
    changed = dict(sd, b=sd["b"].clone())
    changed["b"][1, 2] = float(np.nextafter(np.float32(changed["b"][1, 2].item()), np.float32(np.inf)))
    assert zoo.weights_digest(changed) != zoo.weights_digest(sd)
    assert zoo.weights_digest({"a": sd["a"].double()}) != zoo.weights_digest({"a": sd["a"]})


def test_weight_average_against_numpy():
    """The average of parameters and BatchNorm statistics after each of a few steps, by hand with the warm-up
    decay min(d, (1 + n) / (10 + n)) of update n (0 after the first copy)."""
    from harness.train import ema_decay, weight_average
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.BatchNorm1d(4))
    ema = weight_average(net, 0.8)
    assert weight_average(net, 0.0) is None
    seen = []
    for _ in range(6):
        with torch.no_grad():
            for p in net.parameters():
                p.add_(torch.randn_like(p))
        net.train()(torch.randn(5, 3))  # moves the running statistics
        seen.append({k: v.detach().numpy().astype(np.float64).copy() for k, v in net.state_dict().items()
                     if v.dtype.is_floating_point})
        ema.update_parameters(net)
    want = dict(seen[0])
    for n, state in enumerate(seen[1:]):
        d = min(0.8, (1 + n) / (10 + n))
        assert ema_decay(0.8, n) == d
        want = {k: d * want[k] + (1 - d) * v for k, v in state.items()}
    got = ema.module.state_dict()
    for k, v in want.items():
        np.testing.assert_allclose(got[k].numpy(), v, rtol=1e-5, atol=1e-6, err_msg=k)


def test_a_training_with_a_weight_average_checkpoints_it_and_resumes_it(tmp_path, monkeypatch):
    """Schedule.ema: the checkpoint's state_dict (what is evaluated and exported) is the average, the network's
    own weights go on in train_state_dict (equal to a training without the average), and a training stopped after
    epoch 1 ends as one that ran through."""
    from dataclasses import replace
    recipe = zoo.resolve("pointpillars", "tiny")
    recipe = replace(recipe, schedule=replace(recipe.schedule, ema=0.9))
    data = write_synthetic_dataset(tmp_path / "data", frames=4, seed=3, val=1)
    whole = torch.load(train(recipe, data, tmp_path / "whole", epochs=2, seed=0, progress=False), weights_only=False)
    assert whole["ema_updates"] == 2 * 2  # 4 frames, batch 2, 2 epochs
    assert any(not torch.equal(v, whole["train_state_dict"][k]) for k, v in whole["state_dict"].items())
    model, _ = zoo.load_checkpoint(tmp_path / "whole" / "checkpoint.pt")
    assert all(torch.equal(v, whole["state_dict"][k]) for k, v in model.state_dict().items())
    train_stopped_after_epoch_1(monkeypatch, recipe, data, tmp_path / "parts", epochs=2, seed=0, progress=False)
    parts = torch.load(train(recipe, data, tmp_path / "parts", epochs=2, seed=0, progress=False), weights_only=False)
    for entry in ("state_dict", "train_state_dict"):
        for k, v in whole[entry].items():
            assert torch.equal(v, parts[entry][k]), (entry, k)
    plain = torch.load(train("pointpillars", data, tmp_path / "plain", profile="tiny", epochs=2, seed=0,
                             progress=False), weights_only=False)
    assert "train_state_dict" not in plain and plain["config_hash"] != whole["config_hash"]
    # the average leaves the steps alone: the network's own weights are those of a training without it, bit for
    # bit (benchmarks/levers.py scores both from one training)
    for k, v in plain["state_dict"].items():
        assert torch.equal(v, whole["train_state_dict"][k]), k


def test_amp_is_refused_on_a_cpu_without_native_bf16(tmp_path, capsys, monkeypatch):
    """train --amp bf16 where neither avx512_bf16 nor amx_bf16 is present: exit 2 naming both flags, nothing written."""
    from harness.cli import main
    monkeypatch.setattr(torch.cpu, "get_capabilities",
                        lambda: {"cpu_name": "Test CPU", "avx2": True, "avx512_bf16": False, "amx_bf16": False})
    data = write_synthetic_dataset(tmp_path / "data", frames=2, seed=6)
    assert main(["--quiet", "train", "--model", "pointpillars", "--profile", "tiny", "--data", str(data),
                 "--out", str(tmp_path / "run"), "--amp", "bf16"]) == 2
    err = capsys.readouterr().err
    assert "--amp bf16: Test CPU has no native bfloat16" in err and "avx512_bf16 / amx_bf16" in err
    assert not (tmp_path / "run").exists()


@pytest.mark.skipif(not native_bf16(),
                    reason="this CPU has no native bfloat16 (avx512_bf16 / amx_bf16): train --amp is refused here")
def test_a_bf16_training_checkpoints_float32_weights(tmp_path):
    """Schedule.amp: the checkpoint's weights and optimizer state are float32 and the training is validated (in
    float32, outside the autocast of its steps)."""
    from dataclasses import replace
    recipe = zoo.resolve("pointpillars", "tiny")
    data = write_synthetic_dataset(tmp_path / "data", frames=3, seed=3, val=1)
    state = torch.load(train(replace(recipe, schedule=replace(recipe.schedule, amp="bf16")), data, tmp_path / "amp",
                             epochs=1, seed=0, progress=False), weights_only=False)
    assert np.isfinite(state["final_loss"]) and "val_ap" in state
    assert all(v.dtype == torch.float32 for v in state["state_dict"].values() if v.is_floating_point())
    assert all(v.dtype == torch.float32 for s in state["optimizer"]["state"].values() for v in s.values()
               if torch.is_tensor(v) and v.is_floating_point())


class _GroundTruthNet(torch.nn.Module):
    """Detects each frame's ground-truth boxes (found by the frame's points), shifted by a per-frame
    offset along x: a detector whose AP differs from frame to frame."""

    uses_camera = False

    def __init__(self, ds, shifts):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(1))
        self.by_points = {ds[i].points.tobytes(): (ds[i].gt_boxes, shifts[i]) for i in range(len(ds))}

    def forward(self, points):
        boxes, shift = self.by_points[points.numpy().tobytes()]
        boxes = np.array(boxes, np.float32)
        boxes[:, 0] += shift
        return torch.as_tensor(boxes), torch.linspace(0.9, 0.5, len(boxes))


def test_validation_ap_by_group_equals_the_ap_of_the_groups_frames_alone(tmp_path):
    from harness.dataset import KittiDataset
    from harness.train import validation_ap
    data = write_synthetic_dataset(tmp_path / "data", frames=8, seed=3)
    ds = KittiDataset(data, "train")
    net = _GroundTruthNet(ds, shifts=[0.0, 0.0, 0.0, 0.9, 0.3, 0.6, 0.0, 1.5])
    first = {f: "a" if i < 4 else "b" for i, f in enumerate(ds.frame_ids)}
    out = validation_ap(net, data, split="train", groups=first)
    alone = validation_ap(net, data, split="train", max_frames=4)["3d_all"]  # frames 0-3: group "a"
    assert set(out["3d_all_by"]) == {"a", "b"} and set(out["3d_all_distance"]) == {"0-30", "30-50", "50-80"}
    assert out["3d_all_by"]["a"] == pytest.approx(alone, abs=1e-9)
    assert all(0 < ap < 100 for ap in out["3d_all_by"].values()) and out["3d_all_by"]["a"] != out["3d_all_by"]["b"]
    one = validation_ap(net, data, split="train", groups=dict.fromkeys(ds.frame_ids, "all"))
    assert one["3d_all_by"] == {"all": pytest.approx(one["3d_all"], abs=1e-9)}


def test_validation_ap_of_listed_frames_scores_those_frames_whatever_the_split(tmp_path):
    """frame_ids: the frames of the list, across the folder's splits (a run's val set is scored on all of its
    frames, not on its own val split)."""
    from harness.dataset import KittiDataset
    from harness.train import validation_ap
    data = write_synthetic_dataset(tmp_path / "data", frames=8, seed=3, val=3)
    train, val = KittiDataset(data, "train"), KittiDataset(data, "val")
    assert len(train) == 5 and len(val) == 3
    every = [*train.frame_ids, *val.frame_ids]
    net = _GroundTruthNet(KittiDataset(data, "train", frame_ids=every), shifts=[0.0, 0.9, 0.0, 0.3, 0.0, 1.5, 0.6, 0.0])
    out = validation_ap(net, data, frame_ids=every)
    assert out["frames"] == 8
    assert validation_ap(net, data, frame_ids=train.frame_ids) == validation_ap(net, data, split="train")
    assert validation_ap(net, data, frame_ids=val.frame_ids) == validation_ap(net, data)
    assert out["3d_all"] != validation_ap(net, data)["3d_all"]
