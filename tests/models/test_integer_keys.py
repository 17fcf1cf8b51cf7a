"""Integer voxel keys stay integer in the exported graph: the `kitti` grids (90M cells, keys above
2^24, where a float32 Div + Floor rounds) voxelize and build their first strided level's index
tables in onnxruntime exactly as in eager torch, on a simulated scan with points over the whole grid."""
import numpy as np
import onnxruntime as ort
import pytest
import torch

from models import zoo
from models.sparse import SparseTensor, strided_out_coords, strided_table
from models.voxelize import Grid, dynamic_voxelize, hard_voxelize


class _Keys(torch.nn.Module):
    """Voxelization of a `kitti` grid and the index building of its first strided sparse conv."""

    def __init__(self, name: str):
        super().__init__()
        self.cfg = zoo.config(name, "kitti")
        self.grid = Grid(self.cfg.pc_range, self.cfg.voxel_size)
        stage = self.cfg.backbone3d.stages[0]
        self.stride, self.padding = stage.stride, stage.padding

    def forward(self, points):
        if self.cfg.__class__.__name__.startswith("DV"):
            vox = dynamic_voxelize(points, self.grid)
        else:
            vox = hard_voxelize(points, self.grid, self.cfg.max_points, self.cfg.max_voxels)
        x = SparseTensor(vox.points.new_zeros(vox.num_voxels, 1), vox.coords, vox.shape)
        coords, _ = strided_out_coords(x, 3, self.stride, self.padding)
        table = strided_table(x, coords, 3, self.stride, self.padding)
        return vox.coords, vox.point2voxel, vox.slot, coords, table


@pytest.mark.parametrize("name", ["second", "dv_second"])
def test_kitti_voxel_keys_export_exactly(name, simulated_frame, tmp_path):
    model = _Keys(name)
    assert np.prod(model.grid.shape) > 2 ** 24  # the keys a float32 division would round
    rng = np.random.default_rng(5)
    lo, hi = np.array(model.cfg.pc_range[:3]), np.array(model.cfg.pc_range[3:])
    spread = np.c_[rng.uniform(lo, hi, (30000, 3)), rng.uniform(0, 1, 30000)].astype(np.float32)
    points = torch.from_numpy(np.concatenate([simulated_frame, spread]))
    program = torch.export.export(model, (points[:2000],), dynamic_shapes=({0: torch.export.Dim("n", min=0)},),
                                  strict=False)
    onnx_program = torch.onnx.export(program, dynamo=True, verbose=False)
    path = tmp_path / "keys.onnx"
    onnx_program.save(str(path))
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = session.run(None, {session.get_inputs()[0].name: points.numpy()})
    with torch.no_grad():
        want = model(points)
    assert want[0].shape[0] > 20000 and int((want[0][:, 0] * model.grid.shape[1] * model.grid.shape[2]).max()) > 2 ** 24
    for g, w in zip(got, want):  # voxel count, coords, point -> voxel, slots, strided coords and table
        np.testing.assert_array_equal(g, w.numpy())
