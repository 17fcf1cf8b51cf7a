import itertools

import numpy as np
import pytest
import shapely

from harness import gt_database as gtdb
from harness.core import kitti
from harness.core.boxes import corners_3d, points_in_boxes
from harness.dataset import KittiDataset, synthetic_sample, write_synthetic_dataset
from harness.gt_database import GtSamplingConfig, build_database, load_or_build, sample_objects


def _polygon(box):
    """BEV rectangle of a box, built from its centre, size and yaw with shapely's affinity."""
    x, y, _, l, w, _, yaw = map(float, box)
    rect = shapely.box(-l / 2, -w / 2, l / 2, w / 2)
    return shapely.affinity.translate(shapely.affinity.rotate(rect, yaw, origin=(0, 0), use_radians=True), x, y)


def _inside(points, box):
    """(N,) bool: point inside the box (boundary included), by shapely in BEV plus a z test."""
    in_bev = shapely.intersects_xy(_polygon(box), points[:, 0].astype(float), points[:, 1].astype(float))
    return in_bev & (np.abs(points[:, 2].astype(float) - float(box[2])) <= float(box[5]) / 2)


def _inside_points(rng, box, n):
    """(n, 4) points strictly inside a box (LiDAR frame)."""
    local = rng.uniform(-0.45, 0.45, (n, 3)) * box[3:6]
    c, s = np.cos(box[6]), np.sin(box[6])
    xy = np.c_[local[:, 0] * c - local[:, 1] * s, local[:, 0] * s + local[:, 1] * c] + box[:2]
    return np.c_[xy, local[:, 2] + box[2], rng.uniform(0, 1, n)].astype(np.float32)


def _write_frames(root, seed=0, frames=5):
    """KITTI folder: per frame a Car with many points, a Car with 3, a Van, points below them."""
    rng = np.random.default_rng(seed)
    calib = kitti.kitti_calib()
    ids = [f"{i:06d}" for i in range(frames)]
    for i, fid in enumerate(ids):
        boxes = np.array([[10 + 3 * i, -4, -0.9, 4.2, 1.8, 1.5, rng.uniform(-np.pi, np.pi)],
                          [25, 5 + i, -0.9, 4.0, 1.7, 1.5, 0.3], [40, -3, -0.8, 5.0, 2.0, 2.0, 0.1]], np.float32)
        around = boxes[0] * np.array([1, 1, 1, 1.4, 1.4, 1.4, 1], np.float32)  # points in and out of car 0
        points = np.concatenate([_inside_points(rng, boxes[0], 50 + 10 * i), _inside_points(rng, around, 40),
                                 _inside_points(rng, boxes[1], 3),
                                 _inside_points(rng, boxes[2], 30),
                                 np.c_[rng.uniform(0, 60, (800, 2)) - [0, 30], rng.uniform(-3, -2, (800, 1)),
                                       rng.uniform(0, 1, (800, 1))]])
        kitti.write_points(kitti.frame_path(root, "velodyne", fid), points.astype(np.float32))
        kitti.write_calib(kitti.frame_path(root, "calib", fid), calib)
        kitti.write_labels(kitti.frame_path(root, "label_2", fid),
                           kitti.Labels.from_lidar(boxes, calib, ["Car", "Car", "Van"]))
    kitti.write_image_set(root / "ImageSets" / "train.txt", ids)
    return root


def test_database_equals_brute_force_selection(tmp_path):
    root = _write_frames(tmp_path / "d")
    db = build_database(root, GtSamplingConfig(min_points=0))
    ds = KittiDataset(root, "train")
    expected = []
    for i in range(len(ds)):
        s = ds[i]
        for box, name in zip(s.gt_boxes, s.gt_names):
            if name == "Car":
                expected.append((s.frame_id, box, s.points[_inside(s.points, box)]))
    assert len(db) == len(expected) == 10
    for k, (fid, box, pts) in enumerate(expected):
        assert db.frame_ids[k] == fid and db.names[k] == "Car" and db.num_points[k] == len(pts)
        np.testing.assert_array_equal(db.boxes[k], box)
        np.testing.assert_array_equal(db.object_points(k), pts)


def test_database_filters_by_points_difficulty_and_class(tmp_path):
    root = _write_frames(tmp_path / "d")
    db = build_database(root)  # Car, min 5 points: the 3-point cars go
    assert len(db) == 5 and (db.num_points >= 5).all() and set(db.names) == {"Car"}
    both = build_database(root, GtSamplingConfig(classes=("Car", "Van")))
    assert len(both) == 10 and sorted(set(both.names)) == ["Car", "Van"]
    labels = KittiDataset(root, "train").labels(0)
    height = labels.bbox[:, 3] - labels.bbox[:, 1]
    level = np.where(height >= 40, 0, np.where(height >= 25, 1, -1))  # truncation 0, occlusion 0
    np.testing.assert_array_equal(gtdb.kitti_difficulty(labels), level)
    kept = build_database(root, GtSamplingConfig(difficulties=(int(level[0]),), min_points=0))
    assert len(kept) >= 1 and (kept.difficulty == level[0]).all()


def _database(rng, frames=6):
    samples = [synthetic_sample(rng, num_cars=3, extent=30.0, frame_id=f"{i:06d}") for i in range(frames)]
    parts, boxes, fids = [], [], []
    for s in samples:
        for box in s.gt_boxes:
            grown = box.copy()
            grown[3:6] += 0.02
            parts.append(s.points[_inside(s.points, grown)])
            boxes.append(box)
            fids.append(s.frame_id)
    counts = np.array([len(p) for p in parts])
    return gtdb.GtDatabase(np.concatenate(parts), np.r_[0, np.cumsum(counts)], np.array(boxes),
                           np.array(["Car"] * len(boxes)), np.array(fids), counts, np.zeros(len(boxes), int))


def _added_objects(db, out, n_boxes):
    """Database indices of the boxes appended to a frame (matched row by row)."""
    return [int(np.flatnonzero((db.boxes == b).all(1))[0]) for b in out.gt_boxes[n_boxes:]]


@pytest.mark.parametrize("seed", range(4))
def test_sampled_frames_are_consistent(seed):
    rng = np.random.default_rng(seed)
    db = _database(rng)
    frame = synthetic_sample(rng, num_cars=2, extent=30.0, frame_id="000002")
    clutter = np.c_[rng.uniform([0, -8, -1.7, 0], [32, 8, 0, 1], (2000, 4))].astype(np.float32)
    frame.points = np.concatenate([frame.points, clutter])
    out = sample_objects(frame, db, np.random.default_rng(seed), GtSamplingConfig(sample_groups=(("Car", 12),)))
    added = _added_objects(db, out, len(frame.gt_boxes))
    assert len(added) >= 1 and len(out.gt_boxes) <= 12 and list(out.gt_names) == ["Car"] * len(out.gt_boxes)
    assert all(db.frame_ids[i] != frame.frame_id for i in added) and len(set(added)) == len(added)
    for a, b in itertools.combinations(out.gt_boxes, 2):
        assert _polygon(a).intersection(_polygon(b)).area < 1e-9
    kept = out.points[: len(out.points) - sum(db.num_points[i] for i in added)]
    start = len(kept)
    for i, box in zip(added, out.gt_boxes[len(frame.gt_boxes):]):
        pts = out.points[start:start + db.num_points[i]]
        np.testing.assert_array_equal(pts, db.object_points(i))
        grown = box.copy()
        grown[3:6] += 0.02
        assert _inside(pts, grown).all()
        assert not _inside(kept, box).any()
        start += len(pts)
    original_outside = frame.points[~np.any([_inside(frame.points, b) for b in out.gt_boxes[len(frame.gt_boxes):]], 0)]
    np.testing.assert_array_equal(kept, original_outside)


def test_sampling_is_deterministic_and_rejects_overlaps():
    db = _database(np.random.default_rng(0))
    frame = synthetic_sample(np.random.default_rng(9), num_cars=1, extent=30.0, frame_id="x")
    a = sample_objects(frame, db, np.random.default_rng(3))
    b = sample_objects(frame, db, np.random.default_rng(3))
    c = sample_objects(frame, db, np.random.default_rng(4))
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.gt_boxes, b.gt_boxes)
    assert not np.array_equal(a.gt_boxes, c.gt_boxes)
    on_top = gtdb.select(db, np.arange(len(db)) == 0)
    on_top.boxes = frame.gt_boxes.copy()  # the only candidate sits on the frame's own car
    assert sample_objects(frame, on_top, np.random.default_rng(0)) is frame


def test_empty_database_or_full_frame_leaves_the_frame_unchanged():
    db = _database(np.random.default_rng(1))
    frame = synthetic_sample(np.random.default_rng(2), num_cars=3, frame_id="y")
    empty = gtdb.select(db, np.zeros(len(db), bool))
    assert sample_objects(frame, empty, np.random.default_rng(0)) is frame
    full = GtSamplingConfig(sample_groups=(("Car", 3),))
    assert sample_objects(frame, db, np.random.default_rng(0), full) is frame


def test_cache_is_reused_and_rebuilt_when_data_change(tmp_path, monkeypatch):
    root = write_synthetic_dataset(tmp_path / "d", frames=3, seed=0)
    cache = tmp_path / "cache"
    first = load_or_build(root, cache)
    path = cache / "gt_database_train.npz"
    assert path.is_file() and len(first) == 9
    real_build = gtdb.build_database
    monkeypatch.setattr(gtdb, "build_database", lambda *a, **k: pytest.fail("cache not used"))
    np.testing.assert_array_equal(load_or_build(root, cache).points, first.points)
    monkeypatch.setattr(gtdb, "build_database", real_build)
    labels = kitti.read_labels(kitti.frame_path(root, "label_2", "000001"))
    kitti.write_labels(kitti.frame_path(root, "label_2", "000001"), labels.select(np.array([True, False, False])))
    assert len(load_or_build(root, cache)) == 7
    path.write_bytes(b"not a zip file")
    assert len(load_or_build(root, cache)) == 7
    with pytest.raises(ValueError, match="gt_database_train.npz"):
        gtdb.load(path, "another key")


def test_in_any_box_matches_points_in_boxes():
    rng = np.random.default_rng(5)
    for k in (0, 1, 7):
        boxes = np.c_[rng.uniform(-5, 5, (k, 3)), rng.uniform(0.5, 4, (k, 3)), rng.uniform(-np.pi, np.pi, k)]
        points = rng.uniform(-7, 7, (3000, 4)).astype(np.float32)
        points[:50, :3] = boxes[:1, :3] if k else 0  # centres, and corners exactly on the boundary below
        if k:
            points[50:58, :3] = corners_3d(boxes[:1])[0]
        np.testing.assert_array_equal(gtdb.in_any_box(points, boxes), points_in_boxes(points, boxes).any(axis=1))
