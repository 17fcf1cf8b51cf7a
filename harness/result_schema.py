"""The types of the values a report reads from a run's result files, checked once when the run is loaded.

``results.json`` and ``results/<model>.json`` are JSON files that a user may edit or another tool may
write. One that parses but holds, say, ``"kitti": null`` or an AP as a string is reported as a
``KittiError`` naming the file and the key, before any table or figure is built.

A spec is a leaf (``NUMBER``, ``TEXT``, ``ANY``), ``Maybe(spec)`` (the spec or null), a dict of keys
(a key ending in ``?`` may be absent; keys the spec does not list are not checked: the report does not
read them), ``Each(spec)`` (an object whose every value has that shape: per model, weather, stage) or
``ListOf(spec)`` (``ListOf(spec, n)``: of n items). The specs list what ``harness.tables`` and
``harness.report`` read, with the keys they index directly required.
"""
from __future__ import annotations

from dataclasses import dataclass

from harness.core.kitti import KittiError


@dataclass(frozen=True)
class Leaf:
    what: str  # as the error message says it: "a number"
    types: tuple

    def accepts(self, value) -> bool:
        return isinstance(value, self.types) and not (isinstance(value, bool) and int in self.types)


@dataclass(frozen=True)
class Maybe:
    spec: object


@dataclass(frozen=True)
class Each:
    spec: object


@dataclass(frozen=True)
class ListOf:
    spec: object
    length: int | None = None  # None: any length


NUMBER = Leaf("a number", (int, float))  # NaN included (the JSON writer spells it NaN); true and false are not
TEXT = Leaf("a string", (str,))
ANY = Leaf("any value", (object,))
OPT = Maybe(NUMBER)

# ----------------------------------------------------------------------------- results/<model>.json
_DIFFS = {"easy": NUMBER, "moderate": NUMBER, "hard": NUMBER}
_KITTI = {f"{metric}?": {"0.7": {"R11": _DIFFS, "R40": _DIFFS}} for metric in ("bbox", "bev", "3d", "aos")}
_BINS = {"0-30": NUMBER, "30-50": NUMBER, "50-80": NUMBER}
_AT_IOU = {"0.3": NUMBER, "0.5": NUMBER, "0.7": NUMBER}
_RECALL = {"roi?": _AT_IOU, "rcnn?": _AT_IOU}
_GROUP_ROW = {
    "n_frames": NUMBER, "n_car": NUMBER, "headline": {"3d": {"0.7": NUMBER, "0.5": NUMBER}, "bev": {"0.7": NUMBER}},
    "headline_ci95": {"3d": ListOf(NUMBER, 2)}, "headline_ci95_0.5?": {"3d": ListOf(NUMBER, 2)}, "kitti_moderate": {"3d": NUMBER, "bev": NUMBER},
    "distance": {"3d": {"0.7": _BINS}}, "recall": {"rcnn?": {"0.5?": NUMBER, "0.7?": NUMBER}},
    "n_gt_kitti_moderate?": NUMBER, "ci_method?": TEXT, "n_gt?": {"0-30?": NUMBER, "30-50?": NUMBER, "50-80?": NUMBER},
}
_GROUPS = {"column?": TEXT, "rows": Each(_GROUP_ROW)}
RESULTS = {
    "kitti": _KITTI, "headline": {"3d": {"0.7": NUMBER}, "bev?": {"0.7?": OPT}},
    "distance": {"3d?": {"0.7": _BINS}}, "recall": _RECALL,
    "pr_curve?": {"recall": ListOf(NUMBER), "precision": ListOf(NUMBER)},
    "pr_curve_raw?": {"score": ListOf(NUMBER), "recall": ListOf(NUMBER), "precision": ListOf(NUMBER)},
    "n_gt_kitti?": {"easy": NUMBER, "moderate": NUMBER, "hard": NUMBER},
    "groups_by?": Each(_GROUPS), "groups?": Maybe(_GROUPS),
}

# ----------------------------------------------------------------------------- results.json
_AGREEMENT = {"same_boxes?": OPT, "max_abs_score_diff?": OPT, "max_abs_box_diff?": OPT}
_RUNTIME = {
    "onnxruntime?": Maybe({"latency_ms_p50?": OPT, "latency_ms_p90?": OPT, "fps?": OPT}),
    "prediction?": Maybe({"latency_ms_p50?": OPT}),
    "peak_memory_mb?": OPT, "torch_eager_ms_p50?": OPT, "ort_speedup?": OPT, "agreement?": Maybe(_AGREEMENT),
    "openvino?": Maybe({"latency_ms_p50?": OPT, "agreement?": Maybe(_AGREEMENT)}), "machine?": Maybe(TEXT),
}
_SOTIF_ROW = {"threshold?": OPT, "distance_if_no_braking_m?": OPT, "stopping_distance_m?": OPT,
              "time_after_lane_change_s?": OPT}
_SPACE = {"rule": {"k": NUMBER, "window_s": NUMBER, "reaction_s": NUMBER},  # harness.verdict.verdict
          "instances": ListOf({"instance": TEXT, "weather": TEXT, "verdict": TEXT, "preventable": ANY,
                               "margin_m?": OPT, "n_frames": NUMBER}),
          "phantoms": ListOf({"weather": TEXT, "n_frames": NUMBER, "hours": NUMBER, "n_false": NUMBER}),
          "frames": Each(ListOf(ANY))}
_RELIABILITY = {"ece": OPT, "n": NUMBER,  # harness.calibration.reliability
                "bins": {"count": ListOf(NUMBER), "confidence": ListOf(OPT), "accuracy": ListOf(OPT)}}
_VAL = {"3d_moderate?": OPT, "n_frames?": OPT}  # the run's val set (harness.valset)
_MODEL = {
    "results": TEXT, "size_mb?": OPT, "params?": OPT, "runtime?": _RUNTIME, "sotif?": Maybe(Each(_SOTIF_ROW)),
    "train?": Maybe({"seconds?": OPT, "epochs?": OPT, "val_ap?": Maybe({"3d_moderate?": OPT}),
                     "val_history?": Maybe(ListOf(ANY))}),
    "provenance?": Maybe(Each(ANY)), "sotif_space?": Maybe(Each(_SPACE)),
    "calibration?": Maybe(Each(Each(_RELIABILITY))), "val?": Maybe(_VAL),
}
_DRAW = {"seed": ANY, "tag?": TEXT, "val_ap?": Maybe({"3d_moderate?": OPT}), "val?": Maybe(_VAL),
         "val_history?": Maybe(ListOf(ANY)),
         "headline?": Maybe({"3d?": Maybe({"0.7?": OPT}), "bev?": Maybe({"0.7?": OPT})})}
SUMMARY = {
    "models": Each(_MODEL), "data?": {f"n_{split}_frames?": OPT for split in ("test", "val", "train")},
    "stage_seconds?": Maybe(Each(NUMBER)), "wall_seconds?": OPT, "draws?": Maybe(Each(ListOf(_DRAW))),
}


def _kind(value) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    return {dict: "an object", list: "a list", str: "a string"}.get(type(value), "a number")


def _what(spec) -> str:
    if isinstance(spec, Leaf):
        return spec.what
    if isinstance(spec, ListOf):
        return "a list" if spec.length is None else f"a list of {spec.length}"
    return "an object"


def _matches(value, spec) -> bool:
    """Whether ``value`` itself (not what it holds) has ``spec``'s type."""
    if isinstance(spec, Leaf):
        return spec.accepts(value)
    if isinstance(spec, ListOf):
        return isinstance(value, list) and spec.length in (None, len(value))
    return isinstance(value, dict)


def check(path, value, spec, key: str = "") -> None:
    """Raise ``KittiError(path, ...)`` at the first value under ``key`` that does not have ``spec``'s shape."""
    nullable = isinstance(spec, Maybe)
    if nullable:
        if value is None:
            return
        spec = spec.spec
    if not _matches(value, spec):
        kind = f"a list of {len(value)}" if isinstance(value, list) and isinstance(spec, ListOf) else _kind(value)
        raise KittiError(path, f"{key!r} is {kind}, expected {_what(spec)}{' or null' if nullable else ''}")
    if isinstance(spec, ListOf):
        for i, v in enumerate(value):
            check(path, v, spec.spec, f"{key}[{i}]")
    elif isinstance(spec, Each):
        for k, v in value.items():
            check(path, v, spec.spec, f"{key}.{k}" if key else k)
    elif isinstance(spec, dict):
        for name, sub in spec.items():
            k = name.removesuffix("?")
            where = f"{key}.{k}" if key else k
            if k in value:
                check(path, value[k], sub, where)
            elif not name.endswith("?"):
                raise KittiError(path, f"no {where!r} entry")
