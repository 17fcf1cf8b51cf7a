"""The official KITTI object evaluation for class Car, on the CPU.

Pure algorithm functions (no file I/O). The rules are those of KITTI's devkit as implemented by
the community reference (``kitti_object_eval_python``): per-frame greedy matching, Van counted as
"ignored" for Car, DontCare regions absorbing false positives in 2D, detections below the height
limit ignored, thresholds from the scores of matched detections at 41 recall positions, and
precision interpolated to the right. AP11 samples recall 0, 0.1, ..., 1; AP40 skips recall 0.

All frames are packed into flat arrays once (``EvalSet``); every AP is then computed for any
subset of frames (groups, bootstrap resamples) without recomputing overlaps.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from harness.core.boxes import bev_intersection, iou_bev
from harness.core.kitti import Labels

N_SAMPLE_PTS = 41
METRICS = ("bbox", "bev", "3d")


@dataclass(frozen=True)
class Filter:
    """Which objects count (KITTI's difficulty rules plus a distance range)."""

    name: str
    min_height: float = -1.0  # px; ground truth with bbox height <= this is ignored
    max_occlusion: int = 3
    max_truncation: float = 1.0
    min_distance: float = 0.0  # m, ground-plane distance of the box from the camera
    max_distance: float = float("inf")


DIFFICULTIES = (Filter("easy", 40, 0, 0.15), Filter("moderate", 25, 1, 0.30), Filter("hard", 25, 2, 0.50))


@dataclass
class EvalSet:
    """Ground truth and detections of many frames, flattened, with overlaps precomputed."""

    gt_off: np.ndarray  # (F + 1,) start of each frame's ground truth
    dt_off: np.ndarray  # (F + 1,)
    dc_off: np.ndarray  # (F + 1,) DontCare boxes
    ov_off: np.ndarray  # (F + 1,) start of each frame's flattened (D, G) overlap block
    gt_class: np.ndarray  # 1 = Car, 0 = Van (ignored), -1 = other
    gt_height: np.ndarray
    gt_occluded: np.ndarray
    gt_truncated: np.ndarray
    gt_distance: np.ndarray
    gt_alpha: np.ndarray
    dt_class: np.ndarray  # 1 = Car, -1 = other
    dt_height: np.ndarray
    dt_distance: np.ndarray
    dt_alpha: np.ndarray
    dt_score: np.ndarray
    dt_bbox: np.ndarray  # (D, 4)
    dc_bbox: np.ndarray  # (C, 4)
    overlaps: dict  # metric -> flat float64 array
    compute_aos: bool

    @property
    def n_frames(self) -> int:
        return len(self.gt_off) - 1


def image_box_overlap(boxes: np.ndarray, query: np.ndarray, criterion: int = -1) -> np.ndarray:
    """(N, K) 2D box overlap; criterion -1: IoU, 0: share of ``boxes``' area, 1: of ``query``'s."""
    boxes, query = np.asarray(boxes, float).reshape(-1, 4), np.asarray(query, float).reshape(-1, 4)
    iw = np.minimum(boxes[:, None, 2], query[None, :, 2]) - np.maximum(boxes[:, None, 0], query[None, :, 0])
    ih = np.minimum(boxes[:, None, 3], query[None, :, 3]) - np.maximum(boxes[:, None, 1], query[None, :, 1])
    inter = np.where((iw > 0) & (ih > 0), iw * ih, 0.0)
    area_b = ((boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]))[:, None]
    area_q = ((query[:, 2] - query[:, 0]) * (query[:, 3] - query[:, 1]))[None]
    ua = {-1: area_b + area_q - inter, 0: np.broadcast_to(area_b, inter.shape),
          1: np.broadcast_to(area_q, inter.shape)}[criterion]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(inter > 0, inter / ua, 0.0)


def _camera_boxes(labels: Labels) -> np.ndarray:
    """KITTI camera boxes as rows [x, z, -y_centre, l, w, h, -ry] for the counter-clockwise box
    functions of ``harness.core.boxes``. ``rotation_y`` turns a box about the camera's y axis (down),
    which in the (x, z) plane is clockwise: the reference's ``rbbox_to_corners`` rotates by -ry."""
    h, w, l = labels.dimensions.T
    x, y, z = labels.location.T
    return np.c_[x, z, -(y - h / 2), l, w, h, -labels.rotation_y]


def frame_overlaps(dt: Labels, gt: Labels) -> dict:
    """(D, G) overlaps of one frame for bbox (2D IoU), bev (rotated IoU) and 3d."""
    a, b = _camera_boxes(dt), _camera_boxes(gt)
    out = {"bbox": image_box_overlap(dt.bbox, gt.bbox), "bev": iou_bev(a, b)}
    inter = bev_intersection(a, b)
    top = np.minimum((a[:, 2] + a[:, 5] / 2)[:, None], (b[:, 2] + b[:, 5] / 2)[None])
    bottom = np.maximum((a[:, 2] - a[:, 5] / 2)[:, None], (b[:, 2] - b[:, 5] / 2)[None])
    inter = inter * np.clip(top - bottom, 0, None)
    union = (a[:, 3] * a[:, 4] * a[:, 5])[:, None] + (b[:, 3] * b[:, 4] * b[:, 5])[None] - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        out["3d"] = np.where(inter > 0, inter / union, 0.0)
    return out


def _offsets(sizes) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)


def build_eval_set(gt_annos: list[Labels], dt_annos: list[Labels]) -> EvalSet:
    if len(gt_annos) != len(dt_annos):
        raise ValueError(f"{len(gt_annos)} ground-truth frames but {len(dt_annos)} detection frames")
    cat = lambda arrs, width=None: (np.concatenate(arrs) if arrs else np.zeros((0,) if width is None else (0, width)))
    gt_names = [np.char.lower(np.asarray(g.name, dtype=str)) for g in gt_annos]
    dt_names = [np.char.lower(np.asarray(d.name, dtype=str)) for d in dt_annos]
    ovs = [frame_overlaps(d, g) for d, g in zip(dt_annos, gt_annos)]
    dcs = [g.bbox[n == "dontcare"] for g, n in zip(gt_annos, gt_names)]
    dist = lambda lab: np.hypot(lab.location[:, 0], lab.location[:, 2])
    compute_aos = False
    for d in dt_annos:
        if len(d):
            compute_aos = bool(d.alpha[0] != -10)
            break
    return EvalSet(
        gt_off=_offsets([len(g) for g in gt_annos]), dt_off=_offsets([len(d) for d in dt_annos]),
        dc_off=_offsets([len(c) for c in dcs]), ov_off=_offsets([len(d) * len(g) for d, g in zip(dt_annos, gt_annos)]),
        gt_class=cat([np.where(n == "car", 1, np.where(n == "van", 0, -1)) for n in gt_names]).astype(np.int64),
        gt_height=cat([g.bbox[:, 3] - g.bbox[:, 1] for g in gt_annos]),
        gt_occluded=cat([g.occluded for g in gt_annos]).astype(np.int64),
        gt_truncated=cat([g.truncated for g in gt_annos]), gt_distance=cat([dist(g) for g in gt_annos]),
        gt_alpha=cat([g.alpha for g in gt_annos]),
        dt_class=cat([np.where(n == "car", 1, -1) for n in dt_names]).astype(np.int64),
        dt_height=cat([np.abs(d.bbox[:, 3] - d.bbox[:, 1]) for d in dt_annos]),
        dt_distance=cat([dist(d) for d in dt_annos]), dt_alpha=cat([d.alpha for d in dt_annos]),
        dt_score=cat([d.score if d.score is not None else np.zeros(len(d)) for d in dt_annos]),
        dt_bbox=cat([d.bbox for d in dt_annos], 4), dc_bbox=cat(dcs, 4),
        overlaps={m: cat([o[m].ravel() for o in ovs]).astype(np.float64) for m in METRICS},
        compute_aos=compute_aos)


def ignore_flags(es: EvalSet, f: Filter) -> tuple[np.ndarray, np.ndarray]:
    """KITTI's clean_data for class Car: gt 0 valid / 1 ignored / -1 not considered;
    detections 0 valid / 1 ignored / -1 other class."""
    in_range = lambda d: (d >= f.min_distance) & (d < f.max_distance)
    hard = ((es.gt_occluded > f.max_occlusion) | (es.gt_truncated > f.max_truncation)
            | (es.gt_height <= f.min_height) | ~in_range(es.gt_distance))
    gt = np.where((es.gt_class == 1) & ~hard, 0, np.where((es.gt_class == 0) | (es.gt_class == 1), 1, -1))
    small = (es.dt_height < f.min_height) | ~in_range(es.dt_distance)
    dt = np.where(small, 1, np.where(es.dt_class == 1, 0, -1))
    return gt.astype(np.int64), dt.astype(np.int64)


@numba.njit(cache=True, error_model="numpy")
def _frame_statistics(f, es_off, ov, gt_ign, dt_ign, dt_score, gt_alpha, dt_alpha, dt_bbox, dc_bbox,
                      metric, min_overlap, thresh, compute_fp, compute_aos, thr_out):
    """KITTI's compute_statistics for frame f. Returns tp, fp, fn, similarity, n thresholds."""
    gt_off, dt_off, dc_off, ov_off = es_off
    g0, ng = gt_off[f], gt_off[f + 1] - gt_off[f]
    d0, nd = dt_off[f], dt_off[f + 1] - dt_off[f]
    o0 = ov_off[f]
    assigned = np.zeros(nd, dtype=np.bool_)
    below = np.zeros(nd, dtype=np.bool_)
    if compute_fp:
        for j in range(nd):
            below[j] = dt_score[d0 + j] < thresh
    no_det = -10000000.0
    tp, fp, fn, n_thr, n_delta = 0, 0, 0, 0, 0
    delta = np.zeros(ng)
    for i in range(ng):
        if gt_ign[g0 + i] == -1:
            continue
        det_idx, valid, max_ov, assigned_ignored = -1, no_det, 0.0, False
        for j in range(nd):
            if dt_ign[d0 + j] == -1 or assigned[j] or below[j]:
                continue
            overlap = ov[o0 + j * ng + i]
            score = dt_score[d0 + j]
            if not compute_fp and overlap > min_overlap and score > valid:
                det_idx, valid = j, score
            elif compute_fp and overlap > min_overlap and (overlap > max_ov or assigned_ignored) \
                    and dt_ign[d0 + j] == 0:
                max_ov, det_idx, valid, assigned_ignored = overlap, j, 1.0, False
            elif compute_fp and overlap > min_overlap and valid == no_det and dt_ign[d0 + j] == 1:
                det_idx, valid, assigned_ignored = j, 1.0, True
        if valid == no_det and gt_ign[g0 + i] == 0:
            fn += 1
        elif valid != no_det and (gt_ign[g0 + i] == 1 or dt_ign[d0 + det_idx] == 1):
            assigned[det_idx] = True
        elif valid != no_det:
            tp += 1
            thr_out[n_thr] = dt_score[d0 + det_idx]
            n_thr += 1
            if compute_aos:
                delta[n_delta] = gt_alpha[g0 + i] - dt_alpha[d0 + det_idx]
                n_delta += 1
            assigned[det_idx] = True
    similarity = 0.0
    if compute_fp:
        for j in range(nd):
            if not (assigned[j] or dt_ign[d0 + j] == -1 or dt_ign[d0 + j] == 1 or below[j]):
                fp += 1
        n_stuff = 0
        if metric == 0:
            for c in range(dc_off[f], dc_off[f + 1]):
                for j in range(nd):
                    if assigned[j] or dt_ign[d0 + j] != 0 or below[j]:
                        continue
                    b = dt_bbox[d0 + j]
                    iw = min(b[2], dc_bbox[c, 2]) - max(b[0], dc_bbox[c, 0])
                    ih = min(b[3], dc_bbox[c, 3]) - max(b[1], dc_bbox[c, 1])
                    if iw > 0 and ih > 0 and iw * ih / ((b[2] - b[0]) * (b[3] - b[1])) > min_overlap:
                        assigned[j] = True
                        n_stuff += 1
        fp -= n_stuff
        if compute_aos:
            similarity = -1.0
            if tp > 0 or fp > 0:
                similarity = 0.0
                for k in range(n_delta):
                    similarity += (1.0 + np.cos(delta[k])) / 2.0
    return tp, fp, fn, similarity, n_thr


@numba.njit(cache=True, error_model="numpy")
def _matched_scores(frames, es_off, ov, gt_ign, dt_ign, dt_score, gt_alpha, dt_alpha, dt_bbox, dc_bbox,
                    metric, min_overlap):
    out = np.zeros(max(1, gt_ign.shape[0]))
    buf = np.zeros(max(1, gt_ign.shape[0]))
    n = 0
    for f in frames:
        _, _, _, _, k = _frame_statistics(f, es_off, ov, gt_ign, dt_ign, dt_score, gt_alpha, dt_alpha,
                                          dt_bbox, dc_bbox, metric, min_overlap, 0.0, False, False, buf)
        if n + k > out.shape[0]:  # resampled frames can repeat: grow
            bigger = np.zeros(2 * (n + k))
            bigger[:n] = out[:n]
            out = bigger
        out[n:n + k] = buf[:k]
        n += k
    return out[:n]


@numba.njit(cache=True, error_model="numpy")
def _pr_table(frames, es_off, ov, gt_ign, dt_ign, dt_score, gt_alpha, dt_alpha, dt_bbox, dc_bbox,
              metric, min_overlap, thresholds, compute_aos):
    pr = np.zeros((thresholds.shape[0], 4))
    buf = np.zeros(max(1, gt_ign.shape[0]))
    for f in frames:
        for t in range(thresholds.shape[0]):
            tp, fp, fn, sim, _ = _frame_statistics(f, es_off, ov, gt_ign, dt_ign, dt_score, gt_alpha, dt_alpha,
                                                   dt_bbox, dc_bbox, metric, min_overlap, thresholds[t],
                                                   True, compute_aos, buf)
            pr[t, 0] += tp
            pr[t, 1] += fp
            pr[t, 2] += fn
            if sim != -1.0:
                pr[t, 3] += sim
    return pr


def get_thresholds(scores: np.ndarray, num_gt: int, num_sample_pts: int = N_SAMPLE_PTS) -> np.ndarray:
    """Score thresholds at (about) evenly spaced recall positions, as KITTI's devkit picks them."""
    scores = np.sort(scores)[::-1]
    current_recall, thresholds = 0.0, []
    for i, score in enumerate(scores):
        l_recall = (i + 1) / num_gt
        r_recall = (i + 2) / num_gt if i < len(scores) - 1 else l_recall
        if (r_recall - current_recall) < (current_recall - l_recall) and i < len(scores) - 1:
            continue
        thresholds.append(score)
        current_recall += 1 / (num_sample_pts - 1.0)
    return np.asarray(thresholds, dtype=np.float64)


def _frames(es: EvalSet, frames) -> np.ndarray:
    return np.arange(es.n_frames) if frames is None else np.asarray(frames, dtype=np.int64)


def _kernel_args(es: EvalSet, metric: str, f: Filter, min_overlap: float) -> tuple:
    """The arguments the numba kernels take after ``frames``, up to ``min_overlap``."""
    gt_ign, dt_ign = ignore_flags(es, f)
    return ((es.gt_off, es.dt_off, es.dc_off, es.ov_off), es.overlaps[metric], gt_ign, dt_ign, es.dt_score,
            es.gt_alpha, es.dt_alpha, es.dt_bbox, es.dc_bbox, METRICS.index(metric), float(min_overlap))


def count_gt(es: EvalSet, f: Filter, frames=None) -> int:
    """The Car boxes an AP under filter ``f`` counts in ``frames`` (repeated frames count again)."""
    frame_of_gt = np.repeat(np.arange(es.n_frames), np.diff(es.gt_off))
    return int(np.bincount(frame_of_gt[ignore_flags(es, f)[0] == 0], minlength=es.n_frames)[_frames(es, frames)].sum())


def precision_recall(es: EvalSet, metric: str, f: Filter, min_overlap: float, frames=None,
                     with_aos: bool = False) -> dict:
    """Interpolated precision, recall (and AOS similarity) at the 41 sample points."""
    frames = _frames(es, frames)
    args = _kernel_args(es, metric, f, min_overlap)
    num_gt = count_gt(es, f, frames)
    thresholds = get_thresholds(_matched_scores(frames, *args), num_gt) if num_gt else np.zeros(0)
    pr = _pr_table(frames, *args, thresholds, bool(with_aos and es.compute_aos))
    prec, rec, aos = np.zeros(N_SAMPLE_PTS), np.zeros(N_SAMPLE_PTS), np.zeros(N_SAMPLE_PTS)
    n = len(thresholds)
    with np.errstate(divide="ignore", invalid="ignore"):
        rec[:n] = pr[:, 0] / (pr[:, 0] + pr[:, 2])
        prec[:n] = pr[:, 0] / (pr[:, 0] + pr[:, 1])
        aos[:n] = pr[:, 3] / (pr[:, 0] + pr[:, 1])
    for i in range(n):
        prec[i], rec[i], aos[i] = prec[i:].max(), rec[i:].max(), aos[i:].max()
    return {"precision": prec, "recall": rec, "aos": aos, "thresholds": thresholds, "num_gt": num_gt}


def score_pr_curve(es: EvalSet, metric: str, f: Filter, min_overlap: float, frames=None,
                   max_points: int = 200) -> dict:
    """Precision and recall, not interpolated, at each distinct score of a matched detection (highest
    first): at threshold t the detections scoring >= t are matched as for the AP (``_frame_statistics``).
    More distinct scores than ``max_points`` are thinned evenly, the highest and the lowest kept.
    ``{"score", "precision", "recall"}``: (P,) arrays, empty when nothing matches."""
    frames = _frames(es, frames)
    args = _kernel_args(es, metric, f, min_overlap)
    scores = np.unique(_matched_scores(frames, *args))[::-1]  # (S,) descending
    if len(scores) > max_points:
        scores = scores[np.unique(np.linspace(0, len(scores) - 1, max_points).round().astype(np.int64))]
    pr = _pr_table(frames, *args, np.ascontiguousarray(scores), False)  # (P, 4) tp, fp, fn, similarity
    tp, fp, fn = pr[:, 0], pr[:, 1], pr[:, 2]
    return {"score": scores.copy(), "precision": tp / np.maximum(tp + fp, 1), "recall": tp / np.maximum(tp + fn, 1)}


def ap_r11(prec: np.ndarray) -> float:
    return float(prec[0:N_SAMPLE_PTS:4].sum() / 11 * 100)


def ap_r40(prec: np.ndarray) -> float:
    return float(prec[1:N_SAMPLE_PTS].sum() / 40 * 100)


OVERLAPS = {"0.7": {"bbox": 0.7, "bev": 0.7, "3d": 0.7},
            "0.5": {"bbox": 0.5, "bev": 0.5, "3d": 0.5},
            "official_0.5": {"bbox": 0.7, "bev": 0.5, "3d": 0.5}}


def kitti_ap(es: EvalSet, filters=DIFFICULTIES, overlaps=OVERLAPS, frames=None) -> dict:
    """``{metric: {overlap: {"R11"|"R40": {filter: AP%}}}}`` for bbox, bev, 3d and aos."""
    out: dict = {m: {} for m in (*METRICS, "aos")}
    for key, thr in overlaps.items():
        for metric in METRICS:
            for f in filters:
                pr = precision_recall(es, metric, f, thr[metric], frames, with_aos=metric == "bbox")
                curves = [(metric, pr["precision"])]
                if metric == "bbox" and es.compute_aos:
                    curves.append(("aos", pr["aos"]))
                for name, curve in curves:
                    d = out[name].setdefault(key, {"R11": {}, "R40": {}})
                    d["R11"][f.name], d["R40"][f.name] = ap_r11(curve), ap_r40(curve)
    if not es.compute_aos:
        del out["aos"]
    return out
