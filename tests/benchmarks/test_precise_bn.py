"""benchmarks/precise_bn.py: re-estimated BatchNorm statistics against numpy."""
import numpy as np
import torch
from torch import nn

from benchmarks.precise_bn import batch_norms, recompute_bn_stats
from models.vfe import RowBatchNorm


class Tiny(nn.Module):
    def __init__(self):
        super().__init__()
        self.first = nn.Sequential(nn.Linear(3, 4), RowBatchNorm(4), nn.ReLU())
        self.head = nn.Sequential(nn.Linear(4, 2), nn.BatchNorm1d(2))

    def forward(self, x):
        return self.head(self.first(x))


def _numpy_stats(net: Tiny, batches, eps=1e-5):
    """Per-batch mean / unbiased variance at both BatchNorms, the first normalising with its batch
    statistics (train mode), averaged over the batches."""
    w1, b1 = net.first[0].weight.detach().numpy().astype(np.float64), net.first[0].bias.detach().numpy()
    g1, c1 = net.first[1].weight.detach().numpy(), net.first[1].bias.detach().numpy()
    w2, b2 = net.head[0].weight.detach().numpy().astype(np.float64), net.head[0].bias.detach().numpy()
    s1, s2 = [], []
    for x in batches:
        h1 = x.numpy().astype(np.float64) @ w1.T + b1
        s1.append((h1.mean(0), h1.var(0, ddof=1)))
        a1 = np.maximum((h1 - h1.mean(0)) / np.sqrt(h1.var(0) + eps) * g1 + c1, 0)
        h2 = a1 @ w2.T + b2
        s2.append((h2.mean(0), h2.var(0, ddof=1)))
    return [tuple(np.mean([s[k] for s in stats], 0) for k in range(2)) for stats in (s1, s2)]


def test_recomputed_statistics_are_the_plain_average_of_the_batches():
    torch.manual_seed(0)
    net = Tiny()
    for bn in batch_norms(net):  # stale statistics, as after training
        bn.running_mean.fill_(3.0)
        bn.running_var.fill_(0.1)
    batches = [torch.randn(int(n), 3) * 2 + 1 for n in torch.randint(5, 40, (7,))]
    assert recompute_bn_stats(net, ([b] for b in batches), batch_norms(net)) == 7
    assert not net.training and not any(m.training for m in net.modules())
    for bn, (mean, var) in zip(batch_norms(net), _numpy_stats(net, batches)):
        np.testing.assert_allclose(bn.running_mean.numpy(), mean, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(bn.running_var.numpy(), var, rtol=1e-4, atol=1e-5)


def test_layers_left_out_keep_their_statistics_and_count_no_batch():
    torch.manual_seed(1)
    net = Tiny()
    head = net.head[1]
    head.running_mean.fill_(0.5)
    head.running_var.fill_(2.0)
    only_first = batch_norms(net, ("first",))
    assert only_first == [net.first[1]]
    x = torch.randn(30, 3)
    recompute_bn_stats(net, [[x]], only_first)
    assert head.running_mean.eq(0.5).all() and head.running_var.eq(2.0).all()
    h1 = net.first[0](x)
    np.testing.assert_allclose(net.first[1].running_mean.detach().numpy(), h1.mean(0).detach().numpy(), atol=1e-6)
    # left in eval mode during the pass: no batch counted
    assert head.num_batches_tracked.item() == 0 and net.first[1].num_batches_tracked.item() == 1


def test_augmented_frames_are_the_training_draws_of_their_index(tmp_path):
    from benchmarks.precise_bn import frame_inputs
    from harness.augment import AugmentConfig, augment
    from harness.dataset import KittiDataset, write_synthetic_dataset
    data = write_synthetic_dataset(tmp_path / "data", frames=3, seed=2)
    ds = KittiDataset(data, "train")
    plain = [args[0].numpy() for args in frame_inputs(ds, 5, camera=False)]
    assert len(plain) == 3 and all(np.array_equal(p, ds[i].points) for i, p in enumerate(plain))
    aug = AugmentConfig(flip_y=False, rotation=0.5)
    moved = [args[0].numpy() for args in frame_inputs(ds, 2, camera=False, aug=aug, seed=4)]
    for i, points in enumerate(moved):
        expected = augment(ds[i], np.random.default_rng([4, i]), aug).points
        np.testing.assert_array_equal(points, expected)
        assert not np.allclose(points[:, :2], ds[i].points[:, :2])  # rotated about z
        np.testing.assert_allclose(np.linalg.norm(points[:, :2], axis=1) / np.linalg.norm(ds[i].points[:, :2], axis=1),
                                   np.full(len(points), np.linalg.norm(points[0, :2]) / np.linalg.norm(ds[i].points[0, :2])),
                                   rtol=1e-5)  # one global scale factor
