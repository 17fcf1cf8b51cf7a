"""The study's set and the training set keep their bytes: per-file SHA-256 digests of two small data sets,
made before the scenario space existed, on the two kinds of CPU measured (docs/simulator.md, "The same bytes on
every CPU"): tests/simulator/data/golden_digests.json on an Intel Xeon with AVX-512, golden_digests_avx2.json on
an AMD EPYC with AVX2 only. Their scans, images and per-frame metadata differ (a few rays that meet a triangle's
edge land on the other triangle); their labels, calibrations and split files are the same, and must be on any CPU."""
import hashlib
import json
import os
from pathlib import Path

import pytest

from simulator import generate

DATA = Path(__file__).parent / "data"
GOLDEN = json.loads((DATA / "golden_digests.json").read_text())  # Intel Xeon, AVX-512
KINDS = {"Intel Xeon (AVX-512)": GOLDEN, "AMD EPYC (AVX2)": json.loads((DATA / "golden_digests_avx2.json").read_text())}
# what may differ between CPUs: the scans, the camera images and the per-frame metadata made from them
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
    # on any CPU: the labels, calibrations and splits are the golden ones
    assert [k for k in want if not k.startswith(RAY_CAST) and got[k] != want[k]] == []
    # and the whole set is that of one of the CPU kinds measured
    differ = {kind: [k for k in kept[name] if got[k] != kept[name][k]] for kind, kept in KINDS.items()}
    assert any(not d for d in differ.values()), f"files that differ from each CPU kind's digests: {differ}"


@pytest.mark.parametrize("name", sorted(CASES))
def test_cpu_kinds_differ_only_in_ray_cast_files(name):
    """The two kinds' digests list the same files and differ only in scans, images and their metadata."""
    xeon, epyc = KINDS.values()
    assert sorted(xeon[name]) == sorted(epyc[name])
    assert [k for k in xeon[name] if xeon[name][k] != epyc[name][k] and not k.startswith(RAY_CAST)] == []
