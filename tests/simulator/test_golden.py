"""The study's set and the training set keep their bytes on every CPU: per-file SHA-256 digests of two small
data sets, made before the scenario space existed (tests/simulator/data/golden_digests.json; generator 1.8,
made on an AMD EPYC with AVX2). The ray caster settles every hit in float64 itself (simulator/raycast.py), so
Embree's CPU-dependent rounding does not reach the files (tests/simulator/test_raycast_settle.py makes Embree
propose otherwise, as another CPU's kernels would); docs/simulator.md, "The same bytes on every CPU"."""
import hashlib
import json
import os
from pathlib import Path

import pytest

from simulator import generate

DATA = Path(__file__).parent / "data"
GOLDEN = json.loads((DATA / "golden_digests.json").read_text())
# the files made from ray casts: the scans, the camera images and the per-frame metadata
RAY_CAST = ("training/velodyne/", "training/image_2/", "meta/frames", "meta/dataset.json")
CASES = {"sotif_frames6_ClearNoon_HardRainNight_seed3": dict(preset="sotif", frames=6,
                                                             weathers="ClearNoon,HardRainNight", seed=3),
         "train_frames4_seed5": dict(preset="train", frames=4, seed=5)}


def digests(root: Path) -> dict[str, str]:
    """Every file's SHA-256 (symlinks: their target) under root, the folder lock left out."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        if p.name == ".lock":
            continue
        if p.is_symlink():
            out[rel] = "->" + os.readlink(p)
        elif p.is_file():
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


@pytest.mark.parametrize("name", sorted(CASES))
def test_bytes_match_golden(tmp_path, name):
    kwargs = dict(CASES[name])
    if kwargs["preset"] == "sotif":
        kwargs["instances"] = 1  # the study's protocol, spelled out
    root = generate(tmp_path / "set", progress=False, **kwargs)
    got = digests(root)
    want = GOLDEN[name]
    assert sorted(got) == sorted(want)
    # the labels, calibrations and splits first (they hold without the ray caster), then every file
    assert [k for k in want if not k.startswith(RAY_CAST) and got[k] != want[k]] == []
    assert [k for k in want if got[k] != want[k]] == []
