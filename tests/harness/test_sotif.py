import numpy as np
import pandas as pd
import pytest

from harness import sotif
from harness.core import kitti
from harness.core.kitti import KittiError, Labels

CALIB = kitti.kitti_calib()
SLOW = np.array([0.0, 0.0, -0.9, 4.75, 1.83, 1.45, 0.0], np.float32)  # x filled in per frame
OTHER = np.array([30.0, 3.5, -0.9, 4.2, 1.8, 1.5, 0.0], np.float32)


def _write_frame(root, fid, gt_boxes, pred_boxes, pred_scores, pred_dir):
    kitti.write_calib(kitti.frame_path(root, "calib", fid), CALIB)
    kitti.write_labels(kitti.frame_path(root, "label_2", fid), Labels.from_lidar(gt_boxes, CALIB, ["Car"] * len(gt_boxes)))
    pred = Labels.from_lidar(np.reshape(pred_boxes, (-1, 7)), CALIB, ["Car"] * len(pred_scores), score=pred_scores)
    kitti.write_labels(pred_dir / f"{fid}.txt", pred)


def make_sotif(root, weathers, ego=25.0, slow=60 / 3.6, t_lc=1.0, n=5, ego_speeds=None):
    """Frames at t = 0, 0.5, ... per weather; the slow car (label row 1) approaches from 60 m.

    ``weathers`` maps name -> list of (score, dx) per frame: a prediction on the slow car shifted by dx.
    """
    pred_dir = root / "pred"
    pred_dir.mkdir(parents=True)
    rows, fid_no = [], 0
    for w, preds in weathers.items():
        for k in range(n):
            fid = f"{fid_no:06d}"
            fid_no += 1
            slow_box = SLOW.copy()
            slow_box[0] = 60.0 - 4.0 * k
            shifted = slow_box.copy()
            shifted[0] += preds[k][1]
            _write_frame(root, fid, np.stack([OTHER, slow_box]), shifted, [preds[k][0]], pred_dir)
            rows.append({"frame_id": fid, "split": "test", "weather": w, "scenario_time_s": 0.5 * k,
                         "lane_change_time_s": t_lc, "slow_car_label_index": 1,
                         "ego_speed_mps": ego if ego_speeds is None else ego_speeds[k],
                         "slow_car_speed_mps": slow})
    kitti.write_image_set(root / "ImageSets" / "test.txt", [r["frame_id"] for r in rows])
    kitti.write_frames_meta(root / "meta" / "frames.csv", pd.DataFrame(rows))
    return root, pred_dir


def test_detected_never_and_below_threshold(tmp_path):
    far = 20.0  # a shift that leaves no overlap
    weathers = {
        # a hit before the lane change (t=0) must not count; first hit after it at frame 3 (t=1.5 s)
        "ClearNoon": [(0.9, 0.0), (0.9, far), (0.9, far), (0.9, 0.0), (0.9, 0.0)],
        "HardRainNight": [(0.9, far)] * 5,  # never detected
        "WetSunset": [(0.2, 0.0), (0.2, 0.0), (0.25, 0.0), (0.29, 0.0), (0.31, 0.0)],  # below 0.3 until the end
    }
    root, pred = make_sotif(tmp_path / "d", weathers)
    view = sotif.sotif_view(root, pred, threshold=0.3)
    dv = 25.0 - 60 / 3.6
    clear = view["ClearNoon"]
    assert clear["detected"] and clear["frame_id"] == "000003"
    assert clear["time_after_lane_change_s"] == pytest.approx(0.5)
    front = 4.7 / 2  # the simulated ego's bumper ahead of its LiDAR: gaps are bumper to bumper
    assert sotif.LIDAR_TO_FRONT_M == front
    assert clear["distance_m"] == pytest.approx(60.0 - 12.0 - 4.75 / 2 - front, abs=1e-3)
    d0 = 60.0 - 8.0 - 4.75 / 2 - front  # at the first frame after the lane change (t = 1.0 s)
    assert clear["distance_at_lane_change_m"] == pytest.approx(d0, abs=1e-3)
    assert clear["distance_if_no_braking_m"] == pytest.approx(d0 - dv * 0.5, abs=1e-3)
    assert clear["stopping_distance_m"] == pytest.approx(dv + dv * dv / 8 + 2) and clear["pass"] is True
    assert clear["n_frames_after_lane_change"] == 3
    rain = view["HardRainNight"]
    assert not rain["detected"] and rain["distance_m"] is None and rain["pass"] is False
    wet = view["WetSunset"]
    assert wet["frame_id"] == "000014" and wet["time_after_lane_change_s"] == pytest.approx(1.0)
    assert all(v["threshold"] == 0.3 and v["threshold_source"] == "given" for v in view.values())


def test_fails_when_closing_too_fast(tmp_path):
    root, pred = make_sotif(tmp_path / "d", {"ClearNoon": [(0.9, 0.0)] * 5}, ego=40.0, slow=10.0)
    row = sotif.sotif_view(root, pred, threshold=0.5)["ClearNoon"]
    assert row["stopping_distance_m"] == pytest.approx(30.0 + 900 / 8 + 2)
    assert row["detected"] and row["pass"] is False


def test_verdict_ignores_the_simulated_ego_braking(tmp_path):
    # the data's ego slows to the slow car's speed by frame 4; the verdict keeps dv at the lane change
    speeds = [25.0, 25.0, 25.0, 20.0, 60 / 3.6]
    weathers = {"ClearNoon": [(0.9, 20.0)] * 4 + [(0.9, 0.0)]}
    root, pred = make_sotif(tmp_path / "d", weathers, ego=None, ego_speeds=speeds)
    row = sotif.sotif_view(root, pred, threshold=0.5)["ClearNoon"]
    dv0 = 25.0 - 60 / 3.6
    assert row["closing_speed_mps"] == pytest.approx(dv0)
    assert row["stopping_distance_m"] == pytest.approx(sotif.stopping_distance(dv0))
    d0 = 60.0 - 8.0 - 4.75 / 2 - 4.7 / 2
    assert row["distance_if_no_braking_m"] == pytest.approx(d0 - dv0 * 1.0, abs=1e-3)
    assert sotif.gap_without_braking(10.0, 4.0, 2.0) == 2.0 and sotif.gap_without_braking(10.0, -1.0, 2.0) == 10.0


def test_no_lane_change_gives_no_verdict(tmp_path):
    root, pred = make_sotif(tmp_path / "d", {"ClearNoon": [(0.9, 0.0)] * 5}, t_lc=float("nan"))
    row = sotif.sotif_view(root, pred, threshold=0.5)["ClearNoon"]
    assert row["pass"] is None and row["lane_change_time_s"] is None and row["n_frames_after_lane_change"] == 0


def test_f1_threshold_matches_brute_force():
    rng = np.random.default_rng(3)
    for _ in range(50):
        d = int(rng.integers(0, 30))
        scores = np.round(rng.uniform(0, 1, d), 1)  # ties on purpose
        matched = rng.uniform(size=d) < 0.5
        n_gt = int(matched.sum() + rng.integers(0, 5))
        thr, f1 = sotif.f1_optimal_threshold(scores, matched, n_gt)
        best = (None, 0.0)
        for t in sorted(set(scores.tolist()), reverse=True):
            keep = scores >= t
            tp, fp = int((matched & keep).sum()), int((~matched & keep).sum())
            val = 2 * tp / (2 * tp + fp + (n_gt - tp)) if n_gt else 0.0
            if val > best[1] + 1e-12:
                best = (t, val)
        assert thr == best[0] and f1 == pytest.approx(best[1])


def test_greedy_match_prefers_high_scores():
    gt = np.array([[10, 0, 0, 4, 2, 1.5, 0]], float)
    boxes = np.array([[10.2, 0, 0, 4, 2, 1.5, 0], [10, 0, 0, 4, 2, 1.5, 0]], float)
    assert sotif.greedy_match(boxes, np.array([0.9, 0.5]), gt).tolist() == [True, False]
    assert sotif.greedy_match(boxes, np.array([0.4, 0.5]), gt).tolist() == [False, True]
    assert sotif.greedy_match(boxes[:0], np.zeros(0), gt).shape == (0,)


def test_operating_threshold_from_val(tmp_path):
    root = tmp_path / "d"
    pred = root / "pred"
    pred.mkdir(parents=True)
    assert sotif.operating_threshold(root, pred)[0] == sotif.FALLBACK_THRESHOLD  # no val split
    a, b = SLOW.copy(), OTHER.copy()
    a[0] = 40.0
    fp = a.copy()
    fp[1] += 10.0
    # F1 at 0.9: 2/3; at 0.8: 1/2; at 0.6: 4/5 -> 0.6
    _write_frame(root, "000000", np.stack([a, b]), np.stack([a, fp, b]), [0.9, 0.8, 0.6], pred)
    kitti.write_image_set(root / "ImageSets" / "val.txt", ["000000"])
    thr, source = sotif.operating_threshold(root, pred)
    assert thr == pytest.approx(0.6) and "F1" in source
    kitti.write_image_set(root / "ImageSets" / "val.txt", ["000000", "000001"])
    with pytest.raises(KittiError, match="000001.txt"):
        sotif.operating_threshold(root, pred)


def test_missing_meta_columns_name_the_file(tmp_path):
    root, pred = make_sotif(tmp_path / "d", {"ClearNoon": [(0.9, 0.0)] * 5})
    meta = kitti.read_frames_meta(root / "meta" / "frames.csv").drop(columns=["lane_change_time_s"])
    kitti.write_frames_meta(root / "meta" / "frames.csv", meta)
    with pytest.raises(KittiError, match=r"frames.csv.*lane_change_time_s"):
        sotif.sotif_view(root, pred)
