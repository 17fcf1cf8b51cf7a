"""The simulated data set read the way OpenPCDet's and MMDetection3D's stock info generation reads it.

The steps below re-implement, from their documented behaviour, what ``create_kitti_infos`` (OpenPCDet,
pcdet/datasets/kitti/kitti_dataset.py) and ``create_kitti_info_file`` (MMDetection3D,
tools/dataset_converters/kitti_converter.py) do with a KITTI root: for each of the splits train, val
and test, read ImageSets/<split>.txt, look for the frames in ``testing/`` when the split is named
test and in ``training/`` otherwise, require each frame's image, calib and point cloud there, and, for
train and val, its label file with the objects before the DontCare rows.
"""
import os

import numpy as np
import pytest

from harness.core import kitti
from simulator import generate
from simulator.toolkit_views import VIEW_ROOT

WEATHERS = ["ClearNoon", "HardRainNight"]


def _calib_matrices(path):
    rows = {}
    for line in path.read_text().splitlines():
        if ":" in line:
            key, values = line.split(":", 1)
            rows[key] = np.array(values.split(), float)
    assert rows["P2"].size == 12 and rows["R0_rect"].size == 9 and rows["Tr_velo_to_cam"].size == 12
    return rows


def stock_info_steps(root):
    """The infos a stock tool would write: split -> list of (frame id, number of objects or None)."""
    infos = {}
    for split in ("train", "val", "test"):
        split_file = root / "ImageSets" / f"{split}.txt"
        assert split_file.is_file(), f"{split_file}: the stock tools need it (an empty file is fine)"
        folder = root / ("testing" if split == "test" else "training")
        infos[split] = []
        for fid in [x.strip() for x in split_file.read_text().splitlines()]:
            image = folder / "image_2" / f"{fid}.png"
            assert image.exists(), f"AssertionError: {image}"  # OpenPCDet's get_image_shape
            assert kitti.read_image(image).shape[:2] == (375, 1242)
            _calib_matrices(folder / "calib" / f"{fid}.txt")
            velodyne = folder / "velodyne" / f"{fid}.bin"
            assert velodyne.exists() and velodyne.stat().st_size % 16 == 0  # float32 (N, 4)
            n_objects = None
            if split != "test":  # labelled infos: the label file, objects first, then DontCare
                names = [ln.split()[0] for ln in (folder / "label_2" / f"{fid}.txt").read_text().splitlines()]
                assert names, "np.concatenate over an empty label file fails in get_infos"
                n_objects = sum(n != "DontCare" for n in names)
                assert all(n == "DontCare" for n in names[n_objects:])
            infos[split].append((fid, n_objects))
    return infos


@pytest.fixture(scope="module")
def sotif_set(tmp_path_factory):
    return generate(tmp_path_factory.mktemp("sotif") / "data", "sotif", frames=6, weathers=WEATHERS, seed=5,
                    workers=1, progress=False)


def test_stock_info_generation_runs_on_the_sotif_set(sotif_set):
    test = kitti.read_image_set(sotif_set / "ImageSets" / "test.txt")
    val = kitti.read_image_set(sotif_set / "ImageSets" / "val.txt")
    assert test and kitti.read_image_set(sotif_set / "ImageSets" / "train.txt") == []
    infos = stock_info_steps(sotif_set)
    assert [fid for fid, _ in infos["test"]] == test and [fid for fid, _ in infos["val"]] == val
    # the view root: the labelled test frames as the validation split of a stock config
    view = stock_info_steps(sotif_set / VIEW_ROOT)
    assert view["train"] == [] and view["test"] == [] and [fid for fid, _ in view["val"]] == test
    assert all(n >= 1 for _, n in view["val"])
    for fid in test:  # the same bytes as the data set's own files
        for kind in kitti.KINDS:
            own = kitti.frame_path(sotif_set, kind, fid)
            assert kitti.frame_path(sotif_set / VIEW_ROOT, kind, fid).read_bytes() == own.read_bytes()


def test_views_are_relative_links_inside_the_data_set(sotif_set, tmp_path):
    links = sorted(p for p in sotif_set.rglob("*") if p.is_symlink())
    test = kitti.read_image_set(sotif_set / "ImageSets" / "test.txt")
    assert len(links) == 8 * len(test)  # testing/ without labels, the view root with them and the planes
    for p in links:
        target = os.readlink(p)
        assert not os.path.isabs(target) and p.resolve().is_relative_to(sotif_set.resolve() / "training")
    # folders a tool writes into (velodyne_reduced, gt_database) are real folders, not links into training/
    assert not any(p.is_symlink() for p in (sotif_set / "testing", sotif_set / VIEW_ROOT / "training"))
    # moved elsewhere, the data set keeps working; generated again, the links are the same
    moved = tmp_path / "moved"
    os.rename(sotif_set, moved)
    try:
        stock_info_steps(moved)
        stock_info_steps(moved / VIEW_ROOT)
        again = generate(tmp_path / "again", "sotif", frames=6, weathers=WEATHERS, seed=5, workers=1, progress=False)
        mine = {str(p.relative_to(moved)): os.readlink(p) for p in moved.rglob("*") if p.is_symlink()}
        theirs = {str(p.relative_to(again)): os.readlink(p) for p in again.rglob("*") if p.is_symlink()}
        assert mine == theirs and not list(again.rglob("*.tmp"))
    finally:
        os.rename(moved, sotif_set)


def test_fewer_frames_leave_no_dangling_link_and_training_scenes_need_no_view(tmp_path):
    out = generate(tmp_path / "s", "sotif", frames=6, weathers=WEATHERS, seed=5, workers=1, progress=False)
    generate(out, "sotif", frames=4, weathers=WEATHERS, seed=5, workers=1, progress=False, force=True)
    links = [p for p in out.rglob("*") if p.is_symlink()]
    assert links and all(p.exists() for p in links)
    stock_info_steps(out)
    stock_info_steps(out / VIEW_ROOT)
    train = generate(tmp_path / "t", "train", frames=3, seed=1, workers=1, progress=False)
    infos = stock_info_steps(train)
    assert infos["train"] and infos["test"] == [] and not (train / VIEW_ROOT / "ImageSets").exists()


def _road_plane_as_openpcdet_reads_it(path):
    """OpenPCDet's KittiDataset.get_road_plane: line 4, normal flipped to point up (y < 0), unit length."""
    plane = np.array([float(v) for v in path.read_text().splitlines()[3].split()])
    plane = -plane if plane[1] > 0 else plane
    return plane / np.linalg.norm(plane[:3])


def test_road_planes_lie_on_the_simulated_road_and_under_every_car(sotif_set):
    """The planes OpenPCDet's ground-truth sampler (USE_ROAD_PLANE) reads: one per frame, on the road
    the LiDAR sees and under the labelled cars, computed here from the raw calib matrices."""
    frames = sorted(p.stem for p in (sotif_set / "training" / "velodyne").glob("*.bin"))
    assert sorted(p.stem for p in (sotif_set / "training" / "planes").glob("*.txt")) == frames
    test = kitti.read_image_set(sotif_set / "ImageSets" / "test.txt")
    assert sorted(p.stem for p in (sotif_set / VIEW_ROOT / "training" / "planes").iterdir()) == sorted(test)
    n_cars = 0
    for fid in frames:
        a, b, c, d = _road_plane_as_openpcdet_reads_it(sotif_set / "training" / "planes" / f"{fid}.txt")
        m = _calib_matrices(sotif_set / "training" / "calib" / f"{fid}.txt")
        r0, tr = m["R0_rect"].reshape(3, 3), m["Tr_velo_to_cam"].reshape(3, 4)
        pts = np.fromfile(sotif_set / "training" / "velodyne" / f"{fid}.bin", np.float32).reshape(-1, 4)[:, :3]
        near = pts[(pts[:, 0] > 5) & (pts[:, 0] < 40) & (np.abs(pts[:, 1]) < 8)].astype(np.float64)
        rect = (near @ tr[:, :3].T + tr[:, 3]) @ r0.T
        height = rect @ np.array([a, b, c]) + d  # above the road > 0: the normal points up
        assert np.mean(np.abs(height) < 0.03) > 0.5  # most returns ahead are road returns, on the plane
        assert np.percentile(height, 1) > -0.05  # and nothing lies below it
        # OpenPCDet's put_boxes_on_road_planes moves a sampled box so that its bottom sits at the
        # plane's y below its centre: for the labelled cars the move is (nearly) nothing
        for line in (sotif_set / "training" / "label_2" / f"{fid}.txt").read_text().splitlines():
            f = line.split()
            if f[0] != "Car":
                continue
            x, y, z = map(float, f[11:14])  # bottom centre, rectified camera frame
            assert abs((-d - a * x - c * z) / b - y) < 0.05
            n_cars += 1
    assert n_cars > 0


def test_planes_follow_the_frames_of_the_data_set(tmp_path):
    out = generate(tmp_path / "s", "train", frames=3, seed=1, workers=1, progress=False)
    assert sorted(p.stem for p in (out / "training" / "planes").glob("*.txt")) == \
        sorted(p.stem for p in (out / "training" / "velodyne").glob("*.bin"))
    generate(out, "train", frames=2, seed=1, workers=1, progress=False, force=True)
    assert sorted(p.stem for p in (out / "training" / "planes").glob("*.txt")) == \
        sorted(p.stem for p in (out / "training" / "velodyne").glob("*.bin"))
    assert len(list((out / "training" / "planes").iterdir())) == 2  # the dropped frame's plane went with it
