"""An independent, loop-per-object port of kitti_object_eval_python's rules for class Car
(``eval.py``: clean_data, compute_statistics_jit with DontCare regions and ignored detections,
get_thresholds, AP over 11 / 40 sample points; ``rotate_iou.py``: rbbox_to_corners), with shapely
for the polygon overlaps. It reads label files itself and shares no code with ``harness``.
Two documented extensions of the harness are followed too: a ground-distance filter and the
"all" filter (2D height, occlusion and truncation off). Slow; for tests only."""
import math
from pathlib import Path

import numpy as np
from shapely.geometry import Polygon

# min 2D height (px), max occlusion, max truncation
FILTERS = {"easy": (40, 0, 0.15), "moderate": (25, 1, 0.3), "hard": (25, 2, 0.5), "all": (-1, 3, 1.0)}
ANY_DISTANCE = (0.0, math.inf)


def read(path) -> list[dict]:
    rows = []
    for line in Path(path).read_text().splitlines():
        t = line.split()
        if not t:
            continue
        v = [float(x) for x in t[1:]]
        rows.append({"name": t[0], "trunc": v[0], "occ": v[1], "alpha": v[2], "bbox": v[3:7],
                     "h": v[7], "w": v[8], "l": v[9], "x": v[10], "y": v[11], "z": v[12], "ry": v[13],
                     "score": v[14] if len(v) > 14 else 0.0})
    return rows


def ground_polygon(o) -> Polygon:
    """rbbox_to_corners on (x, z, l, w, ry): the rectangle turned by [[cos, sin], [-sin, cos]]."""
    c, s = math.cos(o["ry"]), math.sin(o["ry"])
    corners = []
    for a, b in ((1, 1), (1, -1), (-1, -1), (-1, 1)):
        dx, dz = a * o["l"] / 2, b * o["w"] / 2
        corners.append((o["x"] + c * dx + s * dz, o["z"] - s * dx + c * dz))
    return Polygon(corners)


def image_iou(b, q) -> float:
    iw = min(b[2], q[2]) - max(b[0], q[0])
    ih = min(b[3], q[3]) - max(b[1], q[1])
    if iw <= 0 or ih <= 0:
        return 0.0
    return iw * ih / ((b[2] - b[0]) * (b[3] - b[1]) + (q[2] - q[0]) * (q[3] - q[1]) - iw * ih)


def overlap(d, g, metric: str) -> float:
    if metric == "bbox":
        return image_iou(d["bbox"], g["bbox"])
    inter = ground_polygon(d).intersection(ground_polygon(g)).area
    if metric == "bev":
        return inter / (d["l"] * d["w"] + g["l"] * g["w"] - inter) if inter > 0 else 0.0
    # camera y points down: a box spans [y - h, y]
    height = min(d["y"], g["y"]) - max(d["y"] - d["h"], g["y"] - g["h"])
    if height <= 0 or inter <= 0:
        return 0.0
    shared = inter * height
    return shared / (d["l"] * d["w"] * d["h"] + g["l"] * g["w"] * g["h"] - shared)


def clean(gt, dt, level: str, distance=ANY_DISTANCE):
    """clean_data: ground truth 0 = counts, 1 = ignored, -1 = other class; detections alike."""
    min_height, max_occ, max_trunc = FILTERS[level]
    inside = lambda o: distance[0] <= math.hypot(o["x"], o["z"]) < distance[1]
    ignored_gt, ignored_dt, dontcare = [], [], []
    for g in gt:
        name = g["name"].lower()
        valid = 1 if name == "car" else 0 if name == "van" else -1
        ignore = (g["occ"] > max_occ or g["trunc"] > max_trunc or g["bbox"][3] - g["bbox"][1] <= min_height
                  or not inside(g))
        if valid == 1 and not ignore:
            ignored_gt.append(0)
        elif valid == 0 or (ignore and valid == 1):
            ignored_gt.append(1)
        else:
            ignored_gt.append(-1)
        if g["name"] == "DontCare":
            dontcare.append(g["bbox"])
    for d in dt:
        if abs(d["bbox"][3] - d["bbox"][1]) < min_height or not inside(d):
            ignored_dt.append(1)
        else:
            ignored_dt.append(0 if d["name"].lower() == "car" else -1)
    return ignored_gt, ignored_dt, dontcare


def statistics(ov, gt, dt, ignored_gt, ignored_dt, dontcare, metric, min_overlap, thresh, compute_fp):
    """compute_statistics_jit: (tp, fp, fn, similarity, matched scores)."""
    nd = len(dt)
    assigned = [False] * nd
    below = [compute_fp and d["score"] < thresh for d in dt]
    tp = fp = fn = 0
    scores, delta = [], []
    none = -1e7
    for i in range(len(gt)):
        if ignored_gt[i] == -1:
            continue
        det, valid, best, matched_ignored = -1, none, 0.0, False
        for j in range(nd):
            if ignored_dt[j] == -1 or assigned[j] or below[j]:
                continue
            o, s = ov[j][i], dt[j]["score"]
            if not compute_fp and o > min_overlap and s > valid:
                det, valid = j, s
            elif compute_fp and o > min_overlap and (o > best or matched_ignored) and ignored_dt[j] == 0:
                best, det, valid, matched_ignored = o, j, 1, False
            elif compute_fp and o > min_overlap and valid == none and ignored_dt[j] == 1:
                det, valid, matched_ignored = j, 1, True
        if valid == none and ignored_gt[i] == 0:
            fn += 1
        elif valid != none and (ignored_gt[i] == 1 or ignored_dt[det] == 1):
            assigned[det] = True
        elif valid != none:
            tp += 1
            scores.append(dt[det]["score"])
            delta.append(gt[i]["alpha"] - dt[det]["alpha"])
            assigned[det] = True
    similarity = 0.0
    if compute_fp:
        free = lambda j: not (assigned[j] or ignored_dt[j] in (-1, 1) or below[j])
        fp = sum(1 for j in range(nd) if free(j))
        in_dontcare = 0
        if metric == "bbox":
            for region in dontcare:
                for j in range(nd):
                    if not free(j):
                        continue
                    b = dt[j]["bbox"]
                    iw = min(b[2], region[2]) - max(b[0], region[0])
                    ih = min(b[3], region[3]) - max(b[1], region[1])
                    if iw > 0 and ih > 0 and iw * ih / ((b[2] - b[0]) * (b[3] - b[1])) > min_overlap:
                        assigned[j] = True
                        in_dontcare += 1
        fp -= in_dontcare
        similarity = sum((1 + math.cos(x)) / 2 for x in delta) if (tp > 0 or fp > 0) else -1
    return tp, fp, fn, similarity, scores


def thresholds(scores, num_gt, n=41) -> list[float]:
    scores = sorted(scores, reverse=True)
    current, out = 0.0, []
    for i, s in enumerate(scores):
        left = (i + 1) / num_gt
        right = (i + 2) / num_gt if i < len(scores) - 1 else left
        if right - current < current - left and i < len(scores) - 1:
            continue
        out.append(s)
        current += 1 / (n - 1.0)
    return out


def average_precision(gts, dts, metric, min_overlap, level, distance=ANY_DISTANCE, aos=False):
    """(AP11, AP40) in percent."""
    frames = []
    for gt, dt in zip(gts, dts):
        ignored_gt, ignored_dt, dontcare = clean(gt, dt, level, distance)
        ov = [[overlap(d, g, metric) for g in gt] for d in dt]
        frames.append((ov, gt, dt, ignored_gt, ignored_dt, dontcare))
    num_gt = sum(f[3].count(0) for f in frames)
    if num_gt == 0:
        return 0.0, 0.0
    matched = []
    for f in frames:
        matched += statistics(*f, metric, min_overlap, 0.0, False)[4]
    precision, orientation = np.zeros(41), np.zeros(41)
    cuts = thresholds(matched, num_gt)
    for t, cut in enumerate(cuts):
        tp = fp = similarity = 0
        for f in frames:
            a, b, _, s, _ = statistics(*f, metric, min_overlap, cut, True)
            tp, fp = tp + a, fp + b
            similarity += s if s != -1 else 0
        precision[t] = tp / (tp + fp) if tp + fp else np.nan
        orientation[t] = similarity / (tp + fp) if tp + fp else np.nan
    for i in range(len(cuts)):
        precision[i] = np.max(precision[i:])
        orientation[i] = np.max(orientation[i:])
    curve = orientation if aos else precision
    return curve[0:41:4].sum() / 11 * 100, curve[1:41].sum() / 40 * 100


def evaluate_folders(gt_dir, dt_dir, ids) -> dict:
    """Flat ``results.json`` keys -> AP, for kitti.*, headline.* and distance.*."""
    gts = [read(Path(gt_dir) / f"{i}.txt") for i in ids]
    dts = [read(Path(dt_dir) / f"{i}.txt") for i in ids]
    out = {}
    for metric in ("bbox", "bev", "3d"):
        for key, min_overlap in (("0.7", 0.7), ("0.5", 0.5)):
            for level in ("easy", "moderate", "hard"):
                kinds = [(metric, False)] + ([("aos", True)] if metric == "bbox" else [])
                for name, aos in kinds:
                    r11, r40 = average_precision(gts, dts, metric, min_overlap, level, aos=aos)
                    out[f"kitti.{name}.{key}.R11.{level}"] = r11
                    out[f"kitti.{name}.{key}.R40.{level}"] = r40
    for metric in ("bev", "3d"):
        for key, min_overlap in (("0.7", 0.7), ("0.5", 0.5)):
            out[f"headline.{metric}.{key}"] = average_precision(gts, dts, metric, min_overlap, "all")[1]
            for name, distance in (("0-30", (0, 30)), ("30-50", (30, 50)), ("50-80", (50, 80))):
                out[f"distance.{metric}.{key}.{name}"] = average_precision(gts, dts, metric, min_overlap, "all",
                                                                           distance)[1]
    return out
