"""Training levers measured by draws: each model trained with seeds 0..K-1 with and without a lever, and the
spread of its val AP40 3D moderate (the run's 300-frame val set) and headline AP40 3D (all distances, IoU 0.7,
the SOTIF set's test frames) over the draws. A lever is adopted when it narrows the spread at no loss of mean; a
lever that saves time (``amp``) when its mean is not lower.

    python benchmarks/levers.py --run DIR [--models second,pointpillars] [--levers ema,amp] [--seeds 2] [--jobs 2]

``DIR`` (outside the checkout) holds the default run's training, val and SOTIF sets, simulated there on first use
with the run's seeds and keys (``harness.run``: the sample's bytes), one folder per training
(``levers/<model>-<lever>-seed<k>/checkpoint.pt``) and one result file per training (``levers/<...>.json``): an
interrupted benchmark resumes every training and skips every finished one.

Levers: ``ema`` (Schedule.ema = 0.999: the exponential moving average of the weights, evaluated and exported);
``amp`` (Schedule.amp = "bf16": each step's forward pass and loss under bfloat16 autocast, ``harness.amp``; only on
a CPU with native bf16, refused elsewhere); ``scenes`` (``SCENES`` training scenes, the default run's generator and
seed, at the same number of steps: the epochs divided by the ratio of the sets' training frames, rounded; a
schedule whose epochs do not divide is refused; adopted: the default run trains on ``SCENES`` scenes since, so
the lever is refused while it is the default's count, and its draws in docs/performance.md were made when the
default was 300 scenes at 30 / 12 epochs); ``weather`` (the default run's training scenes under the 21
weather presets in turn, in place of the six dry ones: rain, wet roads and night in training; the same steps);
``steps`` (twice the epochs over the same training set: what a longer schedule buys, at twice the training's cost);
``pillars`` (PointPillars only: 0.256 m pillars in place of 0.32 m, the range widened by 0.768 m each side so
that the grid, 320 x 256 cells, divides by the backbone's strides: 1.6x the pseudo-image's cells, output cells of
0.512 m in place of 0.64 m; the same epochs); ``pillars16`` (PointPillars only: the published 0.16 m pillars over
the default range, 512 x 400 cells, 4x the cells and output cells of 0.32 m, at most 24,000 pillars a frame: the
default run's frames hold up to about 11,000 non-empty 0.16 m pillars); ``lr_half`` (half the recipe's peak
learning rate, the same one-cycle shape and steps: whether a model whose per-epoch val swings between draws is
stepping too far).
The weight average does not change a training's steps (the network's own weights of a training with it equal,
bit for bit, those of one without: ``tests/harness/test_train.py``), so the ``ema`` training gives both rows of a
draw: the average and the network's own weights, ``none``. Without ``ema`` among the levers, ``none`` is a training
of its own. Each draw is also scored on the SOTIF frames of each precipitation class (dry, wet, rain) and on the
cars of each distance bin (a second table). Each row records the content digests of the val and SOTIF sets it was
scored on and the number of val frames; a row scored on other bytes (the sets simulated again by another
generator), before that record, or on the val set's 45-frame ``val`` split (rows made before 2026-12-07: the val
set's every frame is the run's val) has what changed scored again on the next run (its first figures kept as
``val_before`` and ``headline_before``); its training is not redone.

Each training is ``harness.train.train`` on the compact profile (the default run's), one thread; ``--jobs``
trainings at once. Prints (and writes to ``DIR/levers/table.md``) a Markdown table: model, lever, draws, val mean /
min / max, headline mean / min / max, training seconds per draw, and each lever's paired difference to ``none``
(mean over seeds of lever minus none, and its min / max).
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

LEVERS = {"none": {}, "ema": {"ema": 0.999}, "amp": {"amp": "bf16"}, "scenes": {}, "weather": {}, "steps": {},
          "pillars": {}, "pillars16": {}, "lr_half": {}}
# levers that change a network's config: per lever, the models it applies to and their config fields
CONFIG_LEVERS = {"pillars": {"pointpillars": {"voxel_size": (0.256, 0.256, 4.0),
                                              "pc_range": (0.0, -32.768, -3.0, 81.92, 32.768, 1.0)}},
                 "pillars16": {"pointpillars": {"voxel_size": (0.16, 0.16, 4.0), "max_voxels": 24000}}}
SCENES = 1800  # the scenes lever's training set: 6x the 300 of the default run then, 30 and 12 epochs becoming 5 and 2


def simulate(run_dir: Path) -> None:
    """The default run's training set (with its 45-frame val split), val set and SOTIF set under ``run_dir``."""
    from harness import run, valset
    from harness.stages import Stages
    cfg = run.PROFILES["default"]
    stages = Stages(run_dir, progress=False)
    run.simulate_set(stages, cfg, run_dir / "data", "train")
    valset.simulate(stages, cfg, run_dir, run.DATA_PARTS)
    run.simulate_set(stages, cfg, run_dir / "data", "sotif")


def scenes_set(run_dir: Path) -> Path:
    """The scenes lever's training set, ``SCENES`` scenes of the training generator with the run's seed."""
    from harness import run
    from harness.stages import Stages
    cfg = replace(run.PROFILES["default"], train_frames=SCENES)
    stages = Stages(run_dir / "scenes", progress=False)
    run.simulate_set(stages, cfg, run_dir / "scenes" / "data", "train")
    return run_dir / "scenes" / "data" / "train"


def weather_set(run_dir: Path) -> Path:
    """The weather lever's training set: the default run's training scenes (generator, seed, count) with the 21
    weather presets in turn (scene i under preset i mod 21) in place of the six dry ones."""
    from harness import run
    from harness.stages import Stages
    from simulator.weather import WEATHER_PRESETS
    stages = Stages(run_dir / "weather", progress=False)
    run.simulate_set(stages, run.PROFILES["default"], run_dir / "weather" / "data", "train", list(WEATHER_PRESETS))
    return run_dir / "weather" / "data" / "train"


def same_steps(epochs: int, frames: int, more_frames: int) -> int:
    """The epochs over ``more_frames`` training frames that take the steps of ``epochs`` over ``frames``."""
    ratio = more_frames / frames
    out = round(epochs / ratio)
    if out < 1 or abs(out * ratio - epochs) > 0.02 * epochs:
        raise ValueError(f"{epochs} epochs over {frames} frames do not divide into whole epochs over {more_frames}")
    return out


def _val(net, run_dir: Path) -> float:
    """val AP3D moderate on every frame of the run's val set (``valset.FRAME_LIST``, as the run scores it)."""
    from harness import valset
    from harness.core.kitti import read_image_set
    from harness.train import validation_ap
    frames = read_image_set(run_dir / valset.FRAME_LIST)
    return validation_ap(net, run_dir / valset.VAL_DATA, frame_ids=frames)["3d_moderate"]


def _headline(net, run_dir: Path) -> dict:
    """The headline AP3D, and the headline of each precipitation class's SOTIF frames and each distance bin."""
    from harness.core.kitti import read_frames_meta
    from harness.train import validation_ap
    sotif = run_dir / "data" / "sotif"
    meta = read_frames_meta(sotif / "meta" / "frames.csv")
    head = validation_ap(net, sotif, split="test", groups=dict(zip(meta["frame_id"], meta["precipitation_class"])))
    return {"headline": head["3d_all"], "headline_by": {**head["3d_all_by"], **head["3d_all_distance"]}}


def _scores(net, run_dir: Path) -> dict:
    return {"val": _val(net, run_dir), **_headline(net, run_dir)}


def _data_digests(run_dir: Path) -> dict:
    """The content digests of the val and SOTIF sets a draw is scored on (their simulate stages' outputs), and the
    val frames scored (rows before ``val_frames`` was recorded scored the val set's 45-frame ``val`` split)."""
    from harness import valset
    from harness.core.kitti import read_image_set
    from harness.stages import Stages
    stages = Stages(run_dir, progress=False)
    return {"val": stages.outputs_digest("simulate_val"), "sotif": stages.outputs_digest("simulate_sotif"),
            "val_frames": len(read_image_set(run_dir / valset.FRAME_LIST))}


def lever_recipe(model: str, lever: str, profile: str = "compact"):
    """``model``'s recipe in ``profile`` with ``lever``'s schedule and config fields (the epochs of ``steps`` and
    ``scenes`` are set by ``draw``, which knows the training set)."""
    from models import zoo
    recipe = zoo.resolve(model, profile)
    schedule = replace(recipe.schedule, **LEVERS[lever])
    if lever == "lr_half":
        schedule = replace(schedule, lr=schedule.lr / 2)
    recipe = replace(recipe, schedule=schedule)
    if lever in CONFIG_LEVERS:
        recipe = replace(recipe, config=replace(recipe.config, **CONFIG_LEVERS[lever][model]))
    return recipe


def draw(model: str, lever: str, seed: int, run_dir: Path, profile: str = "compact") -> dict:
    """Train (or resume) one draw and score it; ``{lever: scores}``, with ``none`` beside ``ema`` (the same
    training's own weights). Written to ``levers/<model>-<lever>-seed<seed>.json`` and read from there when done."""
    import torch

    from harness.core.files import atomic_write_text
    from harness.train import train
    from models import zoo
    torch.set_num_threads(1)
    name = f"{model}-{lever}-seed{seed}"
    done = run_dir / "levers" / f"{name}.json"
    data_sets = _data_digests(run_dir)
    if done.is_file():
        out = json.loads(done.read_text())
        ckpt = run_dir / "levers" / name / "checkpoint.pt"
        for row in [r for r in out["rows"] if out["rows"][r].get("data") != data_sets]:
            # scored on other val or SOTIF bytes (another generator), on the val set's 45-frame split, or before the
            # record of them: what changed is scored again
            net, _ = zoo.load_checkpoint(ckpt)
            if row == "none" and lever == "ema":
                net.load_state_dict(zoo.read_checkpoint(ckpt)["train_state_dict"])
            old = out["rows"][row]
            was = old.get("data") or {}
            new = {**old, "data": data_sets}
            if {k: was.get(k) for k in ("val", "val_frames")} != {k: data_sets[k] for k in ("val", "val_frames")}:
                new.update(val=_val(net, run_dir), val_before=old.get("val_before", old["val"]))
            if was.get("sotif") != data_sets["sotif"]:
                new.update(**_headline(net, run_dir), headline_before=old.get("headline_before", old["headline"]))
            out["rows"][row] = new
            atomic_write_text(done, json.dumps(out, indent=1))
        return out
    recipe = lever_recipe(model, lever, profile)
    data, epochs = run_dir / "data" / "train", None
    if lever == "scenes":
        from harness.core.kitti import read_image_set
        data = scenes_set(run_dir)
        n_train = [len(read_image_set(d / "ImageSets" / "train.txt")) for d in (run_dir / "data" / "train", data)]
        epochs = same_steps(recipe.schedule.epochs, *n_train)
    elif lever == "weather":
        data = weather_set(run_dir)
    elif lever == "steps":
        epochs = 2 * recipe.schedule.epochs
    ckpt = train(recipe, data, run_dir / "levers" / name, epochs=epochs, seed=seed, progress=False)
    state = zoo.read_checkpoint(ckpt)
    net, _ = zoo.load_checkpoint(ckpt)
    rows = {lever: {**_scores(net, run_dir), "seconds": state["train_seconds"], "data": data_sets}}
    if lever == "ema":
        net.load_state_dict(state["train_state_dict"])
        rows["none"] = {**_scores(net, run_dir), "seconds": state["train_seconds"], "data": data_sets}
    out = {"model": model, "seed": seed, "cpu": torch.cpu.get_capabilities().get("cpu_name"), "rows": rows}
    atomic_write_text(done, json.dumps(out, indent=1))
    return out


def table(results: list[dict], levers: list[str]) -> str:
    """The Markdown table of ``results`` (``draw``'s outputs): per model and lever the draws' spread, and each
    lever's paired difference to ``none``."""
    lines = ["| model | lever | draws | val mean | val min | val max | headline mean | headline min | headline max "
             "| train s / draw | val lever - none: mean (min, max) | headline lever - none: mean (min, max) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for model in dict.fromkeys(r["model"] for r in results):
        by_seed: dict[str, dict[int, dict]] = {}
        for r in results:
            if r["model"] == model:
                for lever, row in r["rows"].items():
                    by_seed.setdefault(lever, {})[r["seed"]] = row
        for lever in ["none", *levers]:
            rows = by_seed.get(lever, {})
            if not rows:
                continue
            val = np.array([v["val"] for v in rows.values()])
            head = np.array([v["headline"] for v in rows.values()])
            cells = [model, lever, str(len(rows)), *(f"{x:.2f}" for x in (val.mean(), val.min(), val.max())),
                     *(f"{x:.2f}" for x in (head.mean(), head.min(), head.max())),
                     f"{np.mean([v['seconds'] for v in rows.values()]):.0f}"]
            for key in ("val", "headline"):
                seeds = sorted(set(rows) & set(by_seed.get("none", {}))) if lever != "none" else []
                d = np.array([rows[s][key] - by_seed["none"][s][key] for s in seeds])
                cells.append(f"{d.mean():+.2f} ({d.min():+.2f}, {d.max():+.2f})" if len(d) else "")
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def table_by_class(results: list[dict]) -> str:
    """The headline AP3D of each draw on the SOTIF frames of each precipitation class and on each distance bin's
    cars (draws scored with them)."""
    rows = sorted(((r["model"], lever, r["seed"], row["headline"], row["headline_by"]) for r in results
                   for lever, row in r["rows"].items() if "headline_by" in row), key=lambda x: x[:3])
    if not rows:
        return ""
    classes = list(dict.fromkeys(c for *_, by in rows for c in by))
    lines = ["| model | lever | seed | headline | " + " | ".join(f"headline {c}" for c in classes) + " |",
             "|---|---|---:|---:|" + "---:|" * len(classes)]
    for model, lever, seed, head, by in rows:
        lines.append(f"| {model} | {lever} | {seed} | {head:.2f} | "
                     + " | ".join(f"{by[c]:.2f}" if c in by else "" for c in classes) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", type=Path, required=True, help="the benchmark's folder (data and trainings)")
    p.add_argument("--models", default="second,pointpillars")
    p.add_argument("--levers", default="ema", help=f"comma-separated, of {', '.join(l for l in LEVERS if l != 'none')}")
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--jobs", type=int, default=2, help="trainings at once, one thread each (default 2)")
    p.add_argument("--profile", default="compact")
    a = p.parse_args(argv)
    levers = a.levers.split(",")
    unknown = sorted(set(levers) - set(LEVERS) | ({"none"} & set(levers)))
    if unknown:
        p.error(f"unknown lever {', '.join(unknown)}; expected of {', '.join(l for l in LEVERS if l != 'none')}")
    models = a.models.split(",")
    for lever in set(levers) & set(CONFIG_LEVERS):
        if set(models) - set(CONFIG_LEVERS[lever]):
            p.error(f"the {lever} lever applies to {', '.join(CONFIG_LEVERS[lever])} only")
    if "scenes" in levers:
        from harness import run
        if run.PROFILES["default"].train_frames == SCENES:
            p.error(f"the scenes lever is adopted: the default run already trains on {SCENES} scenes")
    simulate(a.run)
    if "scenes" in levers:
        scenes_set(a.run)
    if "weather" in levers:
        weather_set(a.run)
    trained = levers if "ema" in levers else ["none", *levers]
    jobs = [(m, lever, s, a.run, a.profile) for s in range(a.seeds) for m in models for lever in trained]
    with ProcessPoolExecutor(a.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        results = list(pool.map(draw, *zip(*jobs)))
    text = table(results, levers)
    cpus = sorted({r["cpu"] or "unknown CPU" for r in results})
    text = f"CPU: {', '.join(cpus)}\n\n" + text
    by_class = table_by_class(results)
    if by_class:
        text += f"\nThe headline by precipitation class of the SOTIF frames and by distance:\n\n{by_class}"
    from harness.core.files import atomic_write_text
    atomic_write_text(a.run / "levers" / "table.md", text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
