"""The report's figures (matplotlib, Agg canvas, PNG bytes), drawn from a run's result files.

Each ``*_figure`` function builds a ``matplotlib.figure.Figure`` from plain data (testable: the
data it shows can be read back from the artists); ``png`` turns it into deterministic PNG bytes.
``bev_frames`` loads the scans, labels and predictions shown in the bird's-eye-view grid.
"""
from __future__ import annotations

import io
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from harness.core.boxes import corners_bev
from harness.core.kitti import frame_path, read_calib, read_image_set, read_labels, read_points

DPI = 90
MODEL_COLOURS = ("#d62728", "#1f77b4", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22")
GT_COLOUR = "#2ca02c"
BEV_RANGE = ((-5.0, 85.0), (-15.0, 15.0))  # (x, y) metres shown in the bird's-eye views
MAX_BEV_POINTS = 30000
DEFAULT_THRESHOLD = 0.3


def png(fig: Figure) -> bytes:
    """PNG bytes of a figure (no timestamp metadata, so equal figures give equal bytes)."""
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, metadata={"Software": None}, bbox_inches="tight")  # no label clipped
    return buf.getvalue()


def colour(i: int) -> str:
    return MODEL_COLOURS[i % len(MODEL_COLOURS)]


# ----------------------------------------------------------------------------- result figures
def heatmap_figure(matrix: pd.DataFrame, title: str, label: str = "AP40 3D @0.7 (%)", vmax: float = 100.0) -> Figure:
    """Rows x columns heat map (rows = weather presets, columns = models) with the values written in."""
    values = matrix.to_numpy(dtype=float)  # (W, M)
    fig = Figure(figsize=(2.0 + 1.3 * values.shape[1], 1.2 + 0.32 * values.shape[0]), layout="constrained")
    ax = fig.add_subplot()
    im = ax.imshow(np.ma.masked_invalid(values), cmap="viridis", vmin=0.0, vmax=vmax, aspect="auto")
    ax.set_xticks(range(values.shape[1]), [str(c) for c in matrix.columns], rotation=30, ha="right")
    ax.set_yticks(range(values.shape[0]), [str(i) for i in matrix.index])
    for (r, c), v in np.ndenumerate(values):
        text = "–" if math.isnan(v) else f"{v:.1f}"
        ax.text(c, r, text, ha="center", va="center", fontsize=8,
                color="white" if math.isnan(v) or v < 0.6 * vmax else "black")
    fig.colorbar(im, ax=ax, label=label, shrink=0.8)
    ax.set_title(title)
    return fig


def scatter_figure(points: pd.DataFrame, x: str, y: str, xlabel: str, ylabel: str, title: str) -> Figure:
    """One labelled point per model (rows of ``points`` with columns model, x, y; ``<y>_lo`` and ``<y>_hi``, when
    present, drawn as a vertical range such as the spread over training draws); log x axis with plain numbers."""
    fig = Figure(figsize=(6.5, 4.2), layout="constrained")
    ax = fig.add_subplot()
    shown = [(i, r) for i, r in enumerate(points.itertuples(index=False))
             if getattr(r, x) is not None and getattr(r, y) is not None and np.isfinite(getattr(r, x))
             and np.isfinite(getattr(r, y))]
    for k, (i, r) in enumerate(sorted(shown, key=lambda p: getattr(p[1], y))):
        xv, yv = getattr(r, x), getattr(r, y)
        ax.scatter([xv], [yv], color=colour(i), s=60, zorder=3)
        lo, hi = getattr(r, f"{y}_lo", np.nan), getattr(r, f"{y}_hi", np.nan)
        if np.isfinite(lo) and np.isfinite(hi):
            ax.plot([xv, xv], [lo, hi], color=colour(i), lw=2, alpha=0.6, gid=f"range:{r.model}")
        below = k % 2  # neighbours in AP alternate above and below their point, so their labels do not collide
        ax.annotate(str(r.model), (xv, yv), textcoords="offset points", xytext=(7, -11 if below else 5), fontsize=9)
    if len(points) and (points[x].dropna() > 0).all() and points[x].notna().any():
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))  # 20, 50, 100: no 10^x notation
        ax.xaxis.set_minor_formatter(NullFormatter())
    ax.margins(x=0.15, y=0.12)
    ax.set(xlabel=xlabel, ylabel=ylabel, title=title)
    ax.grid(True, alpha=0.3)
    return fig


def pr_figure(curves: dict[str, tuple[np.ndarray, np.ndarray]], title: str) -> Figure:
    """Precision over recall per model (``{model: (recall, precision)}`` at each score threshold of the
    matched detections, highest score first: ``pr_curve_raw``), from recall 0 at the first point's
    precision to the model's final recall, which a dotted line marks."""
    fig = Figure(figsize=(6.5, 4.2), layout="constrained")
    ax = fig.add_subplot()
    for i, (name, (rec, prec)) in enumerate(curves.items()):
        rec, prec = np.asarray(rec, dtype=float), np.asarray(prec, dtype=float)  # (P,), (P,)
        if not len(rec):
            continue
        ax.plot(np.r_[0.0, rec], np.r_[prec[0], prec], color=colour(i), label=f"{name} (recall {rec[-1]:.2f})", lw=1.5)
        ax.axvline(rec[-1], color=colour(i), ls=":", lw=0.8)
    ax.set(xlabel="recall", ylabel="precision", xlim=(0, 1.02), ylim=(0, 1.02), title=title)
    ax.grid(True, alpha=0.3)
    if ax.lines:
        ax.legend(fontsize=8, loc="lower left")
    return fig


def distance_figure(ap: pd.DataFrame, title: str) -> Figure:
    """AP per distance bin (columns) per model (rows), one line per model."""
    fig = Figure(figsize=(6.5, 4.2), layout="constrained")
    ax = fig.add_subplot()
    xs = np.arange(ap.shape[1])
    for i, (name, row) in enumerate(ap.iterrows()):
        ax.plot(xs, row.to_numpy(dtype=float), color=colour(i), marker="o", label=str(name))
    ax.set_xticks(xs, [f"{c} m" for c in ap.columns])
    ax.set(xlabel="ground-truth distance", ylabel="AP40 3D @0.7 (%)", ylim=(0, 100), title=title)
    ax.grid(True, alpha=0.3)
    if len(ap):
        ax.legend(fontsize=8)
    return fig


def data_figure(stats: pd.DataFrame) -> Figure:
    """Per weather preset: mean points per frame (bars, top) and mean / max LiDAR range (lines, bottom)."""
    ranges = [c for c in ("mean_range_m_mean", "max_range_m_mean") if c in stats.columns]
    fig = Figure(figsize=(11, 5.5 if ranges else 3.8), layout="constrained")
    axes = fig.subplots(2 if ranges else 1, 1, sharex=True, squeeze=False)[:, 0]
    xs = np.arange(len(stats))
    axes[0].bar(xs, stats["n_points_mean"], color="#7f7f7f")
    axes[0].set(ylabel="points per frame (mean)", title="SOTIF data per weather preset")
    for c, style in zip(ranges, ("o-", "s--")):
        axes[1].plot(xs, stats[c], style, color="#1f77b4", label=c.replace("_m_mean", "").replace("_", " "))
    if ranges:
        axes[1].set(ylabel="point range (m), frame mean")
        axes[1].legend(fontsize=8)
    axes[-1].set_xticks(xs, stats["weather"], rotation=45, ha="right", fontsize=8)
    for ax in axes:
        ax.grid(True, axis="y", alpha=0.3)
    return fig


# ----------------------------------------------------------------------------- bird's-eye views
@dataclass
class BevFrame:
    """What the bird's-eye views show (LiDAR frame, metres): one frame, one panel per model."""

    title: str
    points: np.ndarray  # (N, 4)
    gt: np.ndarray  # (G, 7) Car boxes
    detections: dict = field(default_factory=dict)  # model -> (D, 7) boxes above the operating threshold
    slow_car: np.ndarray | None = None  # (7,) the slow car's ground-truth box, when the meta names it


def _outline(box: np.ndarray) -> np.ndarray:
    """(5, 2) closed BEV outline of one box."""
    c = corners_bev(box.reshape(1, 7))[0]
    return np.vstack([c, c[:1]])


def _bev_axes(ax, frame: BevFrame, name: str | None, i: int, title: str) -> None:
    """One panel: the scan, ground truth (green; the slow car thick and labelled), model ``name``'s detections."""
    pts = frame.points
    ax.scatter(pts[:, 0], pts[:, 1], s=0.05, c="#555555", rasterized=True, linewidths=0)
    for b in frame.gt:
        o = _outline(b)
        ax.plot(o[:, 0], o[:, 1], color=GT_COLOUR, lw=1.2, gid="gt")
    if frame.slow_car is not None:
        o = _outline(frame.slow_car)
        ax.plot(o[:, 0], o[:, 1], color=GT_COLOUR, lw=2.8, gid="slow_car")
        ax.annotate("slow car", (o[:, 0].max(), o[:, 1].max()), xytext=(3, 6), textcoords="offset points",
                    fontsize=8, color="#145a14", fontweight="bold")
    for b in frame.detections.get(name, np.zeros((0, 7))) if name is not None else ():
        o = _outline(b)
        ax.plot(o[:, 0], o[:, 1], color=colour(i), lw=1.2, ls="--", gid=f"det:{name}")
    (x0, x1), (y0, y1) = BEV_RANGE
    ax.set(xlim=(x0, x1), ylim=(y0, y1), aspect="equal", xlabel="x forward (m)", ylabel="y left (m)")
    ax.set_title(title, fontsize=10)
    ax.tick_params(labelsize=7)
    ax.grid(True, alpha=0.25)


def bev_figure(frame: BevFrame, models: list[str], labels: dict | None = None, ncols: int = 2) -> Figure:
    """One bird's-eye-view panel per model of the same frame (x forward to the right, y left up, equal scales):
    points, ground truth (green, the slow car thick), that model's detections (dashed); the scene alone without
    models."""
    panels = list(models) or [None]
    nrows = math.ceil(len(panels) / ncols)
    fig = Figure(figsize=(6.2 * ncols, 2.6 * nrows + 0.7), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for i, (ax, name) in enumerate(zip(axes, panels)):
        _bev_axes(ax, frame, name, i, (labels or {}).get(name, name) if name is not None else "scene")
    for ax in axes[len(panels):]:
        ax.set_axis_off()
    handles = [Line2D([], [], color=GT_COLOUR, lw=1.2, label="ground truth"),
               Line2D([], [], color=GT_COLOUR, lw=2.8, label="slow car (ground truth)"),
               Line2D([], [], color="#333333", ls="--", label="detections above the operating threshold")]
    fig.legend(handles=handles, loc="outside upper center", ncols=3, fontsize=9, title=frame.title, title_fontsize=10)
    return fig


def pick_frames(meta: pd.DataFrame, ids) -> dict[str, str]:
    """One test frame per weather: the first at or after the lane change with the slow car labelled,
    else the middle frame of that weather (``{weather: frame_id}``, data set order)."""
    frames = meta[meta["frame_id"].isin(set(ids))]
    out = {}
    for weather, sub in frames.groupby("weather", sort=False):
        if {"scenario_time_s", "lane_change_time_s", "slow_car_label_index"} <= set(sub.columns):
            after = sub[(sub["scenario_time_s"] >= sub["lane_change_time_s"] - 1e-6) & (sub["slow_car_label_index"] >= 0)]
            if len(after):
                out[str(weather)] = str(after.sort_values("scenario_time_s", kind="stable")["frame_id"].iloc[0])
                continue
        out[str(weather)] = str(sub["frame_id"].iloc[len(sub) // 2])
    return out


def _boxes(path: Path, calib, with_score: bool, threshold: float = 0.0) -> np.ndarray:
    if not path.is_file():
        return np.zeros((0, 7), np.float32)
    labels = read_labels(path, with_score=with_score or None)
    labels = labels.select(np.asarray(labels.name, dtype=str) == "Car")
    if with_score and len(labels):
        labels = labels.select(labels.score >= threshold)
    return labels.to_lidar(calib) if len(labels) else np.zeros((0, 7), np.float32)


def _slow_car(meta: pd.DataFrame, fid: str, path: Path, calib) -> np.ndarray | None:
    """The slow car's (7,) box: row ``slow_car_label_index`` of the frame's label file, None when not named."""
    if "slow_car_label_index" not in meta.columns:
        return None
    k = int(meta.loc[meta["frame_id"] == fid, "slow_car_label_index"].iloc[0])
    labels = read_labels(path)
    return labels.select(np.array([k])).to_lidar(calib)[0] if 0 <= k < len(labels) else None


def rainiest(meta: pd.DataFrame, weathers) -> str:
    """The weather of highest rain rate among ``weathers`` (the first on ties or without a rain-rate column)."""
    weathers = list(weathers)
    if "rain_rate_mmh" not in meta.columns:
        return weathers[0]
    rate = meta.drop_duplicates("weather").set_index("weather")["rain_rate_mmh"]
    return max(weathers, key=lambda w: (rate.get(w, -1.0), -weathers.index(w)))


def bev_frame(run_dir, meta: pd.DataFrame, thresholds: dict[str, float], seed: int = 0) -> BevFrame | None:
    """The frame the bird's-eye views show: the first test frame after the lane change in the rainiest preset,
    its scan (subsampled), GT cars, the slow car, and each model's detections with score >= its threshold
    (``thresholds``: model -> score). None without test frames."""
    data = Path(run_dir) / "data" / "sotif"
    picked = pick_frames(meta, read_image_set(data / "ImageSets" / "test.txt"))
    if not picked:
        return None
    weather = rainiest(meta, picked)
    fid = picked[weather]
    calib = read_calib(frame_path(data, "calib", fid))
    pts = read_points(frame_path(data, "velodyne", fid))
    if len(pts) > MAX_BEV_POINTS:
        pts = pts[np.random.default_rng([seed, int(fid)]).choice(len(pts), MAX_BEV_POINTS, replace=False)]
    dets = {name: _boxes(Path(run_dir) / "predictions" / name / f"{fid}.txt", calib, True, thr)
            for name, thr in thresholds.items()}
    label_path = frame_path(data, "label_2", fid)
    return BevFrame(f"{weather}, frame {fid}", pts, _boxes(label_path, calib, False), dets,
                    _slow_car(meta, fid, label_path, calib))
