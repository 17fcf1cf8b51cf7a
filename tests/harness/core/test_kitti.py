import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from harness.core import kitti
from harness.core.boxes import corners_3d
from harness.core.kitti import KittiError, Labels


def test_points_round_trip_and_errors(tmp_path):
    pts = np.random.default_rng(0).normal(size=(100, 4)).astype(np.float32)
    p = kitti.write_points(tmp_path / "a.bin", pts)
    np.testing.assert_array_equal(kitti.read_points(p), pts)
    (tmp_path / "t.bin").write_bytes(pts.tobytes()[:-3])
    with pytest.raises(KittiError, match=r"t\.bin.*multiple of 16"):
        kitti.read_points(tmp_path / "t.bin")
    bad = pts.copy()
    bad[5, 1] = np.nan
    (tmp_path / "n.bin").write_bytes(bad.tobytes())
    with pytest.raises(KittiError, match=r"n\.bin.*NaN"):
        kitti.read_points(tmp_path / "n.bin")
    with pytest.raises(KittiError, match="not found"):
        kitti.read_points(tmp_path / "missing.bin")
    assert kitti.read_points(kitti.write_points(tmp_path / "e.bin", np.zeros((0, 4)))).shape == (0, 4)


def test_a_scan_with_values_no_lidar_gives_is_refused(tmp_path):
    pts = np.random.default_rng(0).uniform(-50, 50, (100, 4)).astype(np.float32)
    kitti.write_points(tmp_path / "ok.bin", pts)
    np.testing.assert_array_equal(kitti.read_points(tmp_path / "ok.bin"), pts)
    pts[[7, 9], 3] = 3e38  # finite intensities whose sums overflow float32
    pts.tofile(tmp_path / "big.bin")
    with pytest.raises(KittiError, match=r"big\.bin: 2 points hold a value beyond \+-1e\+06 \(first: point 7, "):
        kitti.read_points(tmp_path / "big.bin")


def test_calib_round_trip_and_projection(tmp_path):
    calib = kitti.kitti_calib()
    p = kitti.write_calib(tmp_path / "c.txt", calib)
    back = kitti.read_calib(p)
    np.testing.assert_allclose(back.lidar2img(), calib.lidar2img(), rtol=1e-9)
    pts = np.array([[10.0, 0.0, -0.08], [20.0, 2.0, 1.0]])  # on the optical axis / left and above
    uv, depth = back.project_lidar(pts)
    assert depth[0] == pytest.approx(10 - 0.27)
    assert uv[0] == pytest.approx([1242 / 2 - 0.5, 375 / 2 - 0.5])
    assert uv[1, 0] < uv[0, 0] and uv[1, 1] < uv[0, 1]
    np.testing.assert_allclose(back.rect_to_lidar(back.lidar_to_rect(pts)), pts, atol=1e-9)
    homog = np.c_[pts, np.ones(2)] @ back.lidar2img().T.astype(np.float64)
    np.testing.assert_allclose(homog[:, :2] / homog[:, 2:3], uv, rtol=1e-5)


def test_calib_errors(tmp_path):
    text = (tmp_path / "ok.txt")
    kitti.write_calib(text, kitti.kitti_calib())
    lines = text.read_text().splitlines()
    (tmp_path / "nokey.txt").write_text("\n".join(l for l in lines if not l.startswith("R0_rect")))
    with pytest.raises(KittiError, match=r"nokey\.txt: missing calib key\(s\) R0_rect"):
        kitti.read_calib(tmp_path / "nokey.txt")
    (tmp_path / "short.txt").write_text(lines[2][:40] + "\n")
    with pytest.raises(KittiError, match=r"short\.txt:1: P2: expected 12 numbers"):
        kitti.read_calib(tmp_path / "short.txt")


@pytest.mark.parametrize("key,rank", [("P2", 0), ("R0_rect", 2), ("Tr_velo_to_cam", 0)])
def test_a_singular_calibration_is_refused_naming_the_matrix(tmp_path, key, rank):
    calib = kitti.kitti_calib()
    m = np.array(getattr(calib, key), dtype=np.float64)
    if rank == 0:
        m[:] = 0
    else:
        m[2] = m[0] + m[1]  # a row the others span
    assert np.linalg.matrix_rank(m[:, :3]) == rank  # the reference: numpy's SVD rank
    kitti.write_calib(tmp_path / "c.txt", kitti.Calib(**{**calib.__dict__, key: m}))
    with pytest.raises(KittiError, match=rf"c\.txt: {key}: singular \(its 3x3 part has rank {rank}\)"):
        kitti.read_calib(tmp_path / "c.txt")


@pytest.mark.parametrize("key,scale", [("R0_rect", 2.0), ("R0_rect", 1e-9), ("Tr_velo_to_cam", 1.01)])
def test_a_calibration_rotation_that_scales_is_refused(tmp_path, key, scale):
    calib = kitti.kitti_calib()
    m = np.array(getattr(calib, key), dtype=np.float64)
    m[:, :3] *= scale
    off = np.abs(m[:, :3].T @ m[:, :3] - np.eye(3)).max()  # by hand: |scale^2 - 1| on the diagonal
    assert off == pytest.approx(abs(scale ** 2 - 1))
    kitti.write_calib(tmp_path / "c.txt", kitti.Calib(**{**calib.__dict__, key: m}))
    with pytest.raises(KittiError, match=rf"c\.txt: {key}: its 3x3 part is not a rotation"):
        kitti.read_calib(tmp_path / "c.txt")
    r = np.array([[9.999239e-01, 9.837760e-03, -7.445048e-03], [-9.869795e-03, 9.999421e-01, -4.278459e-03],
                  [7.402527e-03, 4.351614e-03, 9.999631e-01]])  # KITTI's 000000 R0_rect, 7 digits: accepted
    kitti.write_calib(tmp_path / "k.txt", kitti.Calib(**{**calib.__dict__, "R0_rect": r}))
    np.testing.assert_allclose(kitti.read_calib(tmp_path / "k.txt").R0_rect, r)


def test_an_image_must_hold_its_calibrations_principal_point(tmp_path):
    calib = kitti.kitti_calib()
    u, v, w = calib.P2 @ np.array([0.0, 0.0, 1.0, 0.0])  # the optical axis' vanishing point, by hand
    assert 0 < u / w < 1242 and 0 < v / w < 375
    kitti.check_image_fits_calib("i.png", (375, 1242), calib, "c.txt")
    with pytest.raises(KittiError, match=r"i\.png: the image is 50 x 20 pixels, but c\.txt's P2 puts the principal "
                                         r"point at \(\d+\.\d, \d+\.\d\), outside it"):
        kitti.check_image_fits_calib("i.png", (20, 50), calib, "c.txt")
    (tmp_path / "x.png").write_text("not an image")
    with pytest.raises(KittiError, match=r"x\.png: not a readable image"):
        kitti.image_size(tmp_path / "x.png")
    kitti.write_image(tmp_path / "ok.png", np.zeros((20, 50, 3), np.uint8))
    assert kitti.image_size(tmp_path / "ok.png") == (20, 50)
    from PIL import Image
    Image.fromarray(np.full((20, 50), 40000, np.uint16)).save(tmp_path / "deep.png")  # PIL reads it as mode I;16
    with pytest.raises(KittiError, match=r"deep\.png: a I;16 image; expected 8 bits per channel"):
        kitti.read_image(tmp_path / "deep.png")


def test_labels_lidar_camera_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    boxes = np.c_[rng.uniform(5, 60, (20, 1)), rng.uniform(-10, 10, (20, 1)), rng.uniform(-1.5, -0.5, (20, 1)),
                  rng.uniform(3, 5, (20, 1)), rng.uniform(1.5, 2, (20, 1)), rng.uniform(1.3, 2, (20, 1)),
                  rng.uniform(-np.pi, np.pi, (20, 1))].astype(np.float32)
    calib = kitti.kitti_calib()
    labels = Labels.from_lidar(boxes, calib, ["Car"] * 20, score=rng.uniform(size=20))
    back = kitti.read_labels(kitti.write_labels(tmp_path / "l.txt", labels), with_score=True)
    np.testing.assert_allclose(back.to_lidar(calib)[:, :6], boxes[:, :6], atol=2e-4)
    dyaw = np.angle(np.exp(1j * (back.to_lidar(calib)[:, 6] - boxes[:, 6])))
    assert np.abs(dyaw).max() < 2e-4
    # rotation_y = -yaw - pi/2, bottom-centre location, h w l order
    np.testing.assert_allclose(np.cos(labels.rotation_y), np.cos(-boxes[:, 6] - np.pi / 2), atol=1e-6)
    np.testing.assert_allclose(labels.dimensions, boxes[:, [5, 4, 3]], atol=1e-6)
    np.testing.assert_allclose(labels.location[:, 1], -(boxes[:, 2] - boxes[:, 5] / 2) - 0.08, atol=1e-5)
    # projected corners lie inside (or on) the clipped 2D box
    uv, depth = calib.project_lidar(corners_3d(boxes).reshape(-1, 3))
    uv = uv.reshape(20, 8, 2)
    inside = (uv[..., 0] >= labels.bbox[:, None, 0] - 1e-6) | (uv[..., 0] < 0)
    assert inside.all()


def test_label_errors(tmp_path):
    good = "Car 0.00 0 -1.57 100 120 200 180 1.5 1.6 3.9 1.0 1.6 20.0 -1.57"
    cases = {"fields.txt": (good.rsplit(" ", 1)[0], "expected 15 fields"),
             "class.txt": (good.replace("Car", "Bus"), "unknown class 'Bus'"),
             "num.txt": (good.replace("1.5 ", "x "), "must be numbers"),
             "nan.txt": (good.replace("1.5 ", "nan "), "NaN"),
             "occ.txt": (good.replace(" 0 -1.57", " 7 -1.57"), "occluded")}
    for name, (line, msg) in cases.items():
        (tmp_path / name).write_text(good + "\n" + line + "\n")
        with pytest.raises(KittiError, match=rf"{name}:2: .*{msg}"):
            kitti.read_labels(tmp_path / name)
    (tmp_path / "mixed.txt").write_text(good + "\n" + good + " 0.5\n")
    with pytest.raises(KittiError, match="some lines have a score"):
        kitti.read_labels(tmp_path / "mixed.txt")
    (tmp_path / "empty.txt").write_text("")
    assert len(kitti.read_labels(tmp_path / "empty.txt")) == 0


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.text(max_size=300))
def test_parsers_on_garbage_raise_only_kitti_error(tmp_path, text):
    p = tmp_path / "g.txt"
    p.write_bytes(text.encode("utf-8", errors="replace"))
    for reader in (kitti.read_labels, kitti.read_calib, kitti.read_image_set):
        try:
            reader(p)
        except KittiError as e:
            assert "g.txt" in str(e)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.binary(max_size=200))
def test_points_on_garbage_bytes(tmp_path, data):
    p = tmp_path / "g.bin"
    p.write_bytes(data)
    try:
        pts = kitti.read_points(p)
        assert pts.shape[1] == 4 and np.isfinite(pts).all()
    except KittiError as e:
        assert "g.bin" in str(e)


def test_image_sets_meta_and_images(tmp_path):
    kitti.write_image_set(tmp_path / "ImageSets/test.txt", ["000001", "000002"])
    assert kitti.read_image_set(tmp_path / "ImageSets/test.txt") == ["000001", "000002"]
    df = pd.DataFrame({"frame_id": ["000001", "000002"], "weather": ["ClearNoon", "HardRainNight"]})
    kitti.write_frames_meta(tmp_path / "meta/frames.csv", df)
    back = kitti.read_frames_meta(tmp_path / "meta/frames.csv")
    assert back["frame_id"].tolist() == ["000001", "000002"]
    (tmp_path / "split.txt").write_text("000001\n\n000002\n\nabc\n")
    with pytest.raises(KittiError, match=r"split\.txt:5: frame id 'abc' is not a number"):
        kitti.read_image_set(tmp_path / "split.txt")  # the line of the file, blank lines counted
    (tmp_path / "split.txt").write_text("000001\n000002\n000001\n")
    with pytest.raises(KittiError, match=r"split\.txt:3: frame id 000001 is listed twice \(lines 1 and 3\)"):
        kitti.read_image_set(tmp_path / "split.txt")
    with pytest.raises(KittiError, match=r"ImageSets: is a folder"):
        kitti.read_image_set(tmp_path / "ImageSets")
    (tmp_path / "dup.csv").write_text("frame_id,weather\n000001,A\n000002,B\n1,C\n")
    with pytest.raises(KittiError, match=r"dup\.csv: frame_id 000001 appears more than once \(lines 2, 4\)"):
        kitti.read_frames_meta(tmp_path / "dup.csv")
    img = np.random.default_rng(0).integers(0, 255, (8, 10, 3), dtype=np.uint8)
    p = kitti.write_image(tmp_path / "i.png", img)
    np.testing.assert_array_equal(kitti.read_image(p), img)
    assert kitti.write_image(tmp_path / "j.png", img).read_bytes() == p.read_bytes()
    (tmp_path / "bad.png").write_bytes(b"nope")
    with pytest.raises(KittiError, match=r"bad\.png"):
        kitti.read_image(tmp_path / "bad.png")
    assert kitti.frame_path(tmp_path, "velodyne", "000007").name == "000007.bin"
