"""benchmarks/levers.py: the levers that change a network's config build a network that runs, and are refused
for the models they do not apply to; the schedule levers change the recipe's schedule and nothing else."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from benchmarks import levers
from models import zoo


@pytest.mark.parametrize("lever", sorted(levers.CONFIG_LEVERS))
def test_a_config_lever_builds_a_network_whose_grid_divides_by_its_strides(lever):
    for model, fields in levers.CONFIG_LEVERS[lever].items():
        recipe = zoo.resolve(model, "compact")
        cfg = replace(recipe.config, **fields)
        net = zoo.detector_class(model)(cfg).eval()
        lo, hi, size = np.array(cfg.pc_range[:3]), np.array(cfg.pc_range[3:]), np.array(cfg.voxel_size)
        cells = (hi - lo) / size
        np.testing.assert_allclose(cells, np.round(cells), atol=1e-6)  # whole cells
        total_stride = int(np.prod(cfg.strides))
        assert all(int(round(c)) % total_stride == 0 for c in cells[:2])
        rng = np.random.default_rng(0)
        pts = np.concatenate([rng.uniform(lo, hi, (3000, 3)), rng.uniform(0, 1, (3000, 1))], 1).astype(np.float32)
        with torch.no_grad():
            out = net(torch.from_numpy(pts))
        assert all(torch.isfinite(t).all() for t in out)


def test_a_config_lever_is_refused_for_a_model_it_does_not_apply_to(tmp_path, capsys):
    with pytest.raises(SystemExit):
        levers.main(["--run", str(tmp_path), "--models", "second", "--levers", "pillars"])
    assert "applies to pointpillars only" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # refused before anything is simulated


@pytest.mark.parametrize("model", ["point_rcnn", "pointpillars"])
def test_the_lr_half_lever_halves_the_peak_rate_and_keeps_the_rest(model):
    recipe, halved = zoo.resolve(model, "compact"), levers.lever_recipe(model, "lr_half")
    assert halved.schedule.lr == recipe.schedule.lr / 2
    assert replace(halved.schedule, lr=recipe.schedule.lr) == recipe.schedule
    assert halved.config == recipe.config
    assert levers.lever_recipe(model, "none") == recipe
