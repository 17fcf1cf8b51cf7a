"""The study's set and the training set keep their bytes: per-file SHA-256 digests of two small data sets,
made before the scenario space existed (tests/simulator/data/golden_digests.json)."""
import hashlib
import json
import os
from pathlib import Path

import pytest

from simulator import generate

GOLDEN = json.loads((Path(__file__).parent / "data" / "golden_digests.json").read_text())
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
    assert [k for k in want if got[k] != want[k]] == []
