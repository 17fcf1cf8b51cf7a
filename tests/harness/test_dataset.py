import numpy as np
import pytest

from harness.core import kitti
from harness.core.boxes import points_in_boxes
from harness.dataset import KittiDataset, dataset_hash, synthetic_sample, write_synthetic_dataset


def test_synthetic_sample_points_lie_on_cars():
    s = synthetic_sample(np.random.default_rng(0), num_cars=4)
    assert s.points.dtype == np.float32 and s.points.shape[1] == 4 and s.gt_boxes.shape == (4, 7)
    grown = s.gt_boxes.copy()
    grown[:, 3:6] += 0.01
    inside = points_in_boxes(s.points, grown).any(1)
    assert inside.sum() > 500 and np.allclose(s.points[~inside, 2], -1.73)


def test_dataset_reads_samples_like_the_writer(tmp_path):
    root = write_synthetic_dataset(tmp_path / "d", frames=3, seed=1, val=1)
    ds = KittiDataset(root, "train")
    assert len(ds) == 2 and len(KittiDataset(root, "val")) == 1
    sample = ds[1]
    ref = synthetic_sample(np.random.default_rng([1, 1]), frame_id="000001")
    np.testing.assert_array_equal(sample.points, ref.points)
    np.testing.assert_allclose(sample.gt_boxes, ref.gt_boxes, atol=1e-3)
    assert list(sample.gt_names) == ["Car"] * 3 and sample.image is None
    h = dataset_hash(root)
    kitti.write_labels(kitti.frame_path(root, "label_2", "000000"), kitti.Labels.empty())
    assert dataset_hash(root) != h


def test_missing_folder_is_a_clear_error(tmp_path):
    with pytest.raises(kitti.KittiError, match="not found"):
        KittiDataset(tmp_path / "nowhere", "train")


def test_training_labels_are_checked_as_evaluate_checks_them(tmp_path):
    root = write_synthetic_dataset(tmp_path / "d", frames=2, seed=2)
    path = kitti.frame_path(root, "label_2", "000001")
    fields = path.read_text().splitlines()[0].split()
    fields[10] = "-3.9"  # l
    path.write_text(" ".join(fields) + "\n")
    ds = KittiDataset(root, "train")
    assert len(ds[0].gt_boxes) == 3
    with pytest.raises(kitti.KittiError, match=r"000001\.txt:1: box sizes \(h w l\) must be > 0, got [\d.]+ [\d.]+ -3\.9"):
        ds[1]


def test_a_kept_dataset_reads_each_frame_once_within_its_budget(tmp_path, monkeypatch):
    from harness import dataset
    root = write_synthetic_dataset(tmp_path / "d", frames=3)
    plain, kept = KittiDataset(root), KittiDataset(root, keep=True)
    first = kept[1]
    for a, b in zip((plain[1].points, plain[1].gt_boxes, plain[1].gt_names), (first.points, first.gt_boxes, first.gt_names)):
        np.testing.assert_array_equal(a, b)
    kitti.frame_path(root, "velodyne", "000001").unlink()  # a kept frame is not read again
    assert kept[1] is first
    monkeypatch.setattr(dataset, "KEEP_BYTES", 0)  # over the budget: read every time
    small = KittiDataset(root, keep=True)
    small[0]
    kitti.frame_path(root, "velodyne", "000000").unlink()
    with pytest.raises(kitti.KittiError):
        small[0]
