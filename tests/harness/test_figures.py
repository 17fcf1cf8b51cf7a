import io
import re

import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from PIL import Image

from harness import figures, rain_figures
from harness.core import kitti
from harness.core.kitti import Labels


def _png_size(data: bytes) -> tuple[int, int]:
    with Image.open(io.BytesIO(data)) as im:
        assert im.format == "PNG"
        return im.size


def _rect(box):
    """Reference BEV corners of one box by the rotation formula, as a set of rounded points."""
    x, y, _, l, w, _, yaw = box
    c, s = np.cos(yaw), np.sin(yaw)
    pts = [(x + dx * c - dy * s, y + dx * s + dy * c) for dx, dy in ((l / 2, w / 2), (-l / 2, w / 2), (-l / 2, -w / 2), (l / 2, -w / 2))]
    return {(round(a, 4), round(b, 4)) for a, b in pts}


def test_heatmap_shows_the_matrix_and_is_deterministic():
    rng = np.random.default_rng(0)
    m = pd.DataFrame(rng.uniform(0, 100, (5, 3)), index=[f"w{i}" for i in range(5)], columns=["a", "b", "c"])
    m.iloc[2, 1] = np.nan
    fig = figures.heatmap_figure(m, "t")
    shown = fig.axes[0].images[0].get_array()
    assert shown.mask[2, 1] and np.allclose(shown.filled(-1)[~shown.mask], m.to_numpy()[~np.isnan(m.to_numpy())])
    assert [t.get_text() for t in fig.axes[0].get_yticklabels()] == list(m.index)
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert texts[0] == f"{m.iloc[0, 0]:.1f}" and texts[2 * 3 + 1] == "–"
    a, b = figures.png(figures.heatmap_figure(m, "t")), figures.png(figures.heatmap_figure(m, "t"))
    assert a == b and _png_size(a)[0] > 100


def test_pr_distance_scatter_plot_their_data():
    rng = np.random.default_rng(1)
    rec = np.sort(rng.uniform(0.01, 0.8, 30))  # (P,) at each matched score, highest score first
    prec = rng.uniform(0, 1, 30)
    fig = figures.pr_figure({"a": (rec, prec), "none": ([], [])}, "pr")
    curve, final = fig.axes[0].lines[:2]
    x, y = curve.get_data()
    assert np.allclose(x, np.r_[0, rec]) and np.allclose(y, np.r_[prec[0], prec])  # from recall 0 on
    assert np.allclose(final.get_xdata(), rec[-1]) and len(fig.axes[0].lines) == 2  # the final recall, dotted
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == [f"a (recall {rec[-1]:.2f})"]
    ap = pd.DataFrame(rng.uniform(0, 100, (2, 3)), index=["a", "b"], columns=["0-30", "30-50", "50-80"])
    lines = figures.distance_figure(ap, "d").axes[0].lines
    assert np.allclose(lines[1].get_ydata(), ap.loc["b"])
    pts = pd.DataFrame({"model": ["a", "b", "c"], "lat": [10.0, 100.0, np.nan], "ap": [30.0, 60.0, 1.0]})
    ax = figures.scatter_figure(pts, "lat", "ap", "ms", "AP", "s").axes[0]
    offsets = np.vstack([c.get_offsets() for c in ax.collections])
    assert np.allclose(offsets, [[10, 30], [100, 60]]) and ax.get_xscale() == "log"
    _png_size(figures.png(figures.pr_figure({}, "empty")))


def test_data_figure_bars():
    stats = pd.DataFrame({"weather": ["A", "B"], "n_points_mean": [1000.0, 500.0], "mean_range_m_mean": [20.0, 15.0]})
    fig = figures.data_figure(stats)
    assert [p.get_height() for p in fig.axes[0].patches] == [1000.0, 500.0]
    assert np.allclose(fig.axes[1].lines[0].get_ydata(), [20.0, 15.0])


def test_bev_figure_draws_one_panel_per_model_with_boxes_where_they_are():
    rng = np.random.default_rng(2)
    gt = np.c_[rng.uniform(5, 60, (3, 2)), np.zeros(3), rng.uniform(3, 5, 3), rng.uniform(1.5, 2, 3), np.ones(3),
               rng.uniform(-np.pi, np.pi, 3)]
    det = gt[:2] + [0.3, 0, 0, 0, 0, 0, 0]
    frame = figures.BevFrame("w", rng.uniform(0, 50, (100, 4)).astype(np.float32), gt, {"a": det, "b": np.zeros((0, 7))},
                             slow_car=gt[1])
    fig = figures.bev_figure(frame, ["a", "b", "c"], {"a": "Model A"}, ncols=2)
    panels = [ax for ax in fig.axes if ax.axison]
    assert [ax.get_title() for ax in panels] == ["Model A", "b", "c"] and not fig.axes[3].axison
    for ax in panels:
        assert ax.get_xlabel() == "x forward (m)" and ax.get_ylabel() == "y left (m)" and ax.get_aspect() == 1.0
        assert [t.get_text() for t in ax.texts] == ["slow car"]
        slow = [ln for ln in ax.lines if ln.get_gid() == "slow_car"]
        assert len(slow) == 1 and {(round(a, 4), round(b, 4)) for a, b in np.c_[slow[0].get_data()][:4]} == _rect(gt[1])
    ax = panels[0]
    gt_lines = [ln for ln in ax.lines if ln.get_gid() == "gt"]
    assert len(gt_lines) == 3 and len([ln for ln in ax.lines if ln.get_gid() == "det:a"]) == 2
    assert not [ln for ax in panels[1:] for ln in ax.lines if ln.get_gid() == "det:a"]  # each panel its own model
    for ln, box in zip(gt_lines, gt):
        xy = np.c_[ln.get_data()]
        assert np.allclose(xy[0], xy[-1]) and {(round(a, 4), round(b, 4)) for a, b in xy[:4]} == _rect(box)


def test_pick_frames():
    meta = pd.DataFrame({"frame_id": ["000000", "000001", "000002", "000003", "000004", "000005"],
                         "weather": ["A", "A", "A", "B", "B", "B"], "scenario_time_s": [0, 1, 2, 0, 1, 2],
                         "lane_change_time_s": [1.0, 1.0, 1.0, 9.0, 9.0, 9.0], "slow_car_label_index": [0, -1, 0, 0, 0, 0]})
    assert figures.pick_frames(meta, meta.frame_id) == {"A": "000002", "B": "000004"}
    assert figures.pick_frames(meta[["frame_id", "weather"]], ["000000", "000001", "000003"]) == {"A": "000001", "B": "000003"}


def test_bev_frame_reads_the_rainiest_scan_labels_slow_car_and_thresholded_predictions(tmp_path):
    data = tmp_path / "data" / "sotif"
    calib = kitti.kitti_calib()
    gt = np.array([[30.0, 0.5, -0.9, 4.5, 1.8, 1.5, 0.1], [50.0, -3.0, -0.9, 4.0, 1.7, 1.5, 0.0]], np.float32)
    pts = np.random.default_rng(3).uniform(0, 50, (40000, 4)).astype(np.float32)
    rows = []
    for i, (w, rate) in enumerate([("A", 0.0), ("B", 18.0), ("C", 4.5)]):
        fid = f"{i:06d}"
        kitti.write_points(kitti.frame_path(data, "velodyne", fid), pts)
        kitti.write_calib(kitti.frame_path(data, "calib", fid), calib)
        kitti.write_labels(kitti.frame_path(data, "label_2", fid), Labels.from_lidar(gt, calib, ["Van", "Car"]))
        kitti.write_labels(tmp_path / "predictions" / "m" / f"{fid}.txt",
                           Labels.from_lidar(gt, calib, ["Car", "Car"], score=[0.9, 0.2]))
        rows.append({"frame_id": fid, "weather": w, "rain_rate_mmh": rate, "slow_car_label_index": 1})
    kitti.write_image_set(data / "ImageSets" / "test.txt", ["000000", "000001", "000002"])
    f = figures.bev_frame(tmp_path, pd.DataFrame(rows), {"m": 0.5, "missing": 0.5})
    assert f.title == "B, frame 000001"
    assert len(f.points) == figures.MAX_BEV_POINTS and f.gt.shape == (1, 7)  # the Van is not drawn
    np.testing.assert_allclose(f.gt[0], gt[1], atol=1e-3)
    np.testing.assert_allclose(f.slow_car, gt[1], atol=1e-3)  # row 1 of the label file
    assert f.detections["m"].shape == (1, 7) and f.detections["missing"].shape == (0, 7)
    np.testing.assert_allclose(f.detections["m"][0], gt[0], atol=1e-3)
    assert _png_size(figures.png(figures.bev_figure(f, ["m", "missing"])))[1] > 100
    assert figures.rainiest(pd.DataFrame(rows)[["frame_id", "weather"]], ["C", "A"]) == "C"


def test_bev_figure_without_models_shows_the_scene():
    frame = figures.BevFrame("w", np.zeros((0, 4), np.float32), np.zeros((0, 7)))
    fig = figures.bev_figure(frame, [])
    assert [ax.get_title() for ax in fig.axes if ax.axison] == ["scene"]
    _png_size(figures.png(fig))


def test_scatter_ticks_are_plain_numbers_and_ranges_are_drawn():
    pts = pd.DataFrame({"model": ["a", "b"], "lat": [21.0, 120.0], "ap": [70.0, 75.0], "ap_lo": [68.0, np.nan],
                        "ap_hi": [74.0, np.nan]})
    fig = figures.scatter_figure(pts, "lat", "ap", "ms", "AP", "s")
    ax = fig.axes[0]
    FigureCanvasAgg(fig).draw()
    labels = [t.get_text() for t in ax.get_xticklabels() if t.get_text()]
    assert labels and all(re.fullmatch(r"[0-9.]+", t) for t in labels)  # no 10^x
    ranges = [ln for ln in ax.lines if ln.get_gid() == "range:a"]
    assert len(ranges) == 1 and list(ranges[0].get_ydata()) == [68.0, 74.0]
    assert not [ln for ln in ax.lines if ln.get_gid() == "range:b"]
    texts = sorted(ax.texts, key=lambda t: t.get_text())
    assert [t.get_text() for t in texts] == ["a", "b"] and texts[0].xyann[1] != texts[1].xyann[1]  # apart


def test_rain_figure_shows_each_condition_with_its_interval():
    rng = np.random.default_rng(6)
    rows = [{"model": m, "iou": iou, "condition": c, "ap": ap, "ap_lo": ap - 3, "ap_hi": ap + 2}
            for m in ("a", "b") for iou in ("0.5", "0.7") for c in ("dry", "rain", "hard rain")
            for ap in [float(rng.uniform(20, 90))]]
    long = pd.DataFrame(rows)
    fig = rain_figures.rain_figure(long, {"a": "Model A"})
    assert [t.get_text() for t in fig.axes[1].get_xticklabels()] == ["Model A", "b"]
    for ax, iou in zip(fig.axes, ("0.5", "0.7")):
        assert ax.get_ylabel() == f"AP40 3D @{iou} (%)"
        containers = {cont.get_label(): cont for cont in ax.containers}
        for c in ("dry", "rain", "hard rain"):
            data_line, _, (bars,) = containers[c].lines
            ref = long[(long.iou == iou) & (long.condition == c)]
            assert np.allclose(data_line.get_ydata(), ref["ap"])
            assert np.allclose([sorted(seg[:, 1]) for seg in bars.get_segments()], ref[["ap_lo", "ap_hi"]].to_numpy())


def test_delta_heatmap_is_centred_on_zero_and_ordered_blocks_are_separated():
    m = pd.DataFrame({"a": [0.0, -12.5, 3.0], "b": [0.0, np.nan, -4.0]}, index=["ClearNoon", "HardRainNoon", "ClearNight"])
    groups = [("Noon", 0, 2), ("Night", 2, 3)]
    fig = rain_figures.delta_heatmap(m, groups, {"HardRainNoon": 50.0}, "d")
    im = fig.axes[0].images[0]
    assert im.get_clim() == (-12.5, 12.5) and im.get_cmap().name == "RdBu"
    assert [t.get_text() for t in fig.axes[0].get_yticklabels()] == ["ClearNoon", "HardRainNoon (50 mm/h)", "ClearNight"]
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert texts[:4] == ["+0.0", "+0.0", "-12.5", "–"] and {"Noon", "Night"} <= set(texts)
    assert [ln.get_ydata()[0] for ln in fig.axes[0].lines] == [1.5]  # one separator between the two blocks
    fig = rain_figures.ordered_heatmap(m.abs(), groups, {}, "t")
    assert [t.get_text() for t in fig.axes[0].get_yticklabels()] == list(m.index)


def test_pr_figure_of_a_perfect_detector_reaches_recall_1_at_precision_1(tmp_path):
    from harness.eval_kitti import Filter, build_eval_set, score_pr_curve
    calib = kitti.kitti_calib()
    boxes = np.array([[10.0 * (i + 1), 0, -0.9, 4, 1.8, 1.5, 0] for i in range(5)], np.float32)
    gt = Labels.from_lidar(boxes, calib, ["Car"] * 5)
    dt = Labels.from_lidar(boxes, calib, ["Car"] * 5, score=np.linspace(0.9, 0.5, 5))
    raw = score_pr_curve(build_eval_set([gt], [dt]), "3d", Filter("all"), 0.7)
    x, y = figures.pr_figure({"perfect": (raw["recall"], raw["precision"])}, "pr").axes[0].lines[0].get_data()
    assert x[0] == 0 and x[-1] == 1.0 and np.all(y == 1.0) and np.all(np.diff(x) > 0)
