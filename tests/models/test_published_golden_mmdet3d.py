"""The imported DV-SECOND (3-class and Car configs) against golden data of MMDetection3D 1.4's own code
(``benchmarks/golden_mmdet3d.py``: its registry-built detector on CPU, random weights by the
seeded rule in its spconv 2.x checkpoint layout, one frame through its test step on one thread,
where spconv's CPU convolution repeats exactly). The
checkpoint is rebuilt here as MMDetection3D saves it (``meta`` and a ``state_dict`` whose
``_metadata`` marks the sparse convs version 2), imported through ``sotif-bench import``'s code
and run: the bird's-eye map, the class logits and the final Car boxes must match."""
import collections
from pathlib import Path

import pytest
import torch

from benchmarks.golden_weights import fill
from harness.import_weights import import_checkpoint
from models import zoo
from tests.models.test_published_golden import assert_matches_golden, load

GOLDEN = Path(__file__).parents[1] / "golden"


def reference_file(g: dict, path: Path) -> None:
    """The golden weights as an MMDetection3D 1.4 checkpoint (mmengine's save: meta, state_dict)."""
    state = collections.OrderedDict((n, torch.from_numpy(v)) for n, v in
                                    fill([str(n) for n in g["names"]], g["shapes"], int(g["seed"]),
                                         float(g["cls_bias"]), rule=str(g["rule"])).items())
    state._metadata = collections.OrderedDict(
        (str(k), {} if v < 0 else {"version": int(v)}) for k, v in zip(g["meta_keys"], g["meta_versions"]))
    meta = {"mmdet3d_version": "1.4.0", "mmengine_version": "0.10.7", "epoch": 80,
            "dataset_meta": {"classes": [str(c) for c in g["classes"]]}}
    torch.save({"meta": meta, "state_dict": state}, path)


@pytest.mark.parametrize("config", ["", "car"], ids=["3class", "car"])
def test_imported_dv_second_is_mmdet3d(config, tmp_path):
    g = load("mmdet3d", "dv_second", config)
    reference_file(g, tmp_path / "ref.pth")
    import_checkpoint(tmp_path / "ref.pth", "mmdet3d", "dv_second", tmp_path / "ours.pt")
    assert_matches_golden(zoo.load_checkpoint(tmp_path / "ours.pt")[0], g)
