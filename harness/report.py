"""Render a run directory into ``tables/``, ``figures/``, ``report.md`` and a self-contained ``index.html``.

Everything comes from the run's result files (``results.json``, ``results/<model>.json``, the data
set's meta and scans, the prediction files) through ``harness.tables`` and ``harness.figures``; the
jinja2 templates in ``harness/templates`` only lay the prepared tables and figures out. The whole
report is built in memory first and then written file by file atomically, so a bad input (missing or
corrupt ``results.json``, a value of the wrong type in a result file) raises ``KittiError`` naming the file
before anything is written.
"""
from __future__ import annotations

import base64
import os
import re
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
from jinja2 import Environment, FileSystemLoader, StrictUndefined
from markupsafe import Markup

from harness import (data_identity, figures, notes, provenance, rain, rain_figures, report_bounds, report_pairs,
                     report_space, sotif, tables)
from harness.cells import DISTANCE_BINS, mark_capped
from harness.core.files import atomic_write_bytes, atomic_write_text
from harness.groups import headline_matrix
from harness.published_run import published_note

TEMPLATES = Path(__file__).parent / "templates"

SMOKE_BANNER = ("Smoke run: numbers meaningless.",  # (heading, text) on a quick-profile report
                "The quick profile trains tiny models for a few epochs on a few frames to check that the pipeline "
                "runs end to end; `make run` (the default profile) gives results.")

HOW_TO_READ = {  # one sentence opening each section: how to read it
    "rain": "Compare a model's rain cells with its dry cell: a loss counts where the intervals do not overlap. "
            "The IoU 0.5 rows are the figures the summary quotes.",
    "models": "Each row is one detector: compare the SOTIF columns (higher AP and more instances passed are "
              "better, lower latency is cheaper); the val column shows how well each one trained.",
    "main": "Read a row to compare the models in one weather and a column to see how one model's AP falls "
            "from the clear presets to rain; overlapping intervals mark differences the test set cannot "
            "separate.",
    "paper": "These are the figures the source study and KITTI tables report; on the SOTIF set KITTI's filters"
             " drop most of the far, small cars, so compare them with published figures, not across weathers.",
    "sotif": "Look for FAIL cells: each marks a weather in which the model would have found the slow car too "
             "late, or never, for the ego to brake.",
    "robustness": "1.0 means as good as in clear weather and less means worse; mRR condenses a model's rain and wet"
                  " presets into one such number, and only an interval wholly below 1 is a measurable loss.",
    "detail": "Check the cars columns before trusting a small AP: an AP over few cars is capped and noisy.",
    "runtime": "Fewer milliseconds is faster; an ORT speed-up above 1 means onnxruntime beats torch eager, and "
               "the agreement columns should read 1.00 (all frames the same boxes) with tiny score differences.",
    "data": "Fewer points and a shorter mean range show how much a preset took from the sensor before any "
            "detector ran.",
    "stages": "Use it to see where the run's time went.",
    "sotif_space": report_space.HOW_TO_READ,
    "sotif_answer": report_space.ANSWER_HOW_TO_READ,
    "draws": "A difference between two models means something only where it is larger than each model's range "
             "over its training draws, and that range is often wider than the bootstrap interval over frames.",
    **report_pairs.HOW_TO_READ,
}
ACCURACY_SECTIONS = ("main", "paper", "sotif", "robustness", "detail")  # their intros say what a row's training draws are


# Column headers as the reader sees them (the CSV and JSON tables keep the short machine names)
COLUMN_NAMES = {
    "n_frames": "frames", "n_car": "cars", "ap3d": "AP 3D", "ap3d_lo": "AP 3D 95% low", "ap3d_hi": "AP 3D 95% high",
    "ap_bev": "AP BEV", "ap3d_0.5": "AP 3D @0.5", "kitti_mod_3d": "KITTI mod 3D", "kitti_mod_bev": "KITTI mod BEV",
    **{f"ap3d_{b}m": f"AP 3D {b} m" for b in DISTANCE_BINS},
    "n_gt_kitti_mod": "cars KITTI mod", **{f"n_gt_{b}m": f"cars {b} m" for b in DISTANCE_BINS},
    "recall@0.5": "recall @0.5 %", "recall@0.7": "recall @0.7 %",
    **{f"{s}@{t}": f"{s.replace('rcnn', 'RCNN').replace('roi', 'RoI')} @{t}"
       for s in ("roi", "rcnn") for t in ("0.3", "0.5", "0.7")},
    "clean_ap3d": "clean AP 3D", "n_corrupt_presets": "rain/wet presets", "worst_preset": "worst preset",
    "worst_rel": "worst relative AP", "two_stage": "two-stage", "ort_p50_ms": "ORT p50 ms", "ort_p90_ms": "ORT p90 ms",
    "fps": "frames/s", "predict_p50_ms": "ORT p50 ms in prediction", "size_mb": "ONNX MB", "params_m": "params (M)",
    "peak_memory_mb": "peak MB", "torch_p50_ms": "torch p50 ms", "ort_speedup": "ORT speed-up",
    "same_boxes": "same boxes as torch", "max_score_diff": "max score diff",
    "max_box_diff": "max box diff", "train_s": "train s",
    "ov_p50_ms": "OpenVINO p50 ms", "ov_same_boxes": "OpenVINO same boxes",
    "ov_max_box_diff": "OpenVINO max box diff", "ov_error": "OpenVINO error",
    "n_test": "test frames", "n_val": "val frames", "n_points_mean": "points mean", "n_points_min": "points min",
    "n_points_max": "points max", "mean_range_m_mean": "mean range m", "max_range_m_mean": "max range m",
    "ground_share_mean": "ground share", "rain_rate_mmh": "rain mm/h", "fog_density": "fog density",
    "time_of_day": "time of day", "precipitation_class": "precipitation", **report_pairs.COLUMN_NAMES,
}


MODEL_LABELS = {"pointpillars": "PointPillars", "second": "SECOND", "dv_second": "DV-SECOND", "parta2": "Part-A2",
                "pv_rcnn": "PV-RCNN", "point_rcnn": "PointRCNN", "mvx_net": "MVX-Net"}


def readable(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` as a reader sees it: headers in words (``COLUMN_NAMES``, the models' published names, any other
    underscore as a space) and the models' published names in a ``model`` column."""
    out = df.rename(columns=lambda c: str(COLUMN_NAMES.get(c, MODEL_LABELS.get(c, c))).replace("_", " "))
    if "model" in out.columns:
        out["model"] = out["model"].map(lambda m: MODEL_LABELS.get(m, m) if isinstance(m, str) else m)
    return out


@dataclass
class Section:
    """One block of the report: a heading, how to read it, what it shows, tables and figures."""

    key: str
    title: str
    intro: str
    tables: list  # (caption, DataFrame, decimals)
    figures: list  # figure names (keys of the rendered figure dict)
    details: bool = False  # long tables folded away in the HTML
    figures_first: bool = False
    notes: tuple = ()  # short statements of what the numbers do not say, printed below the intro
    lead: bool = False  # shown first, above the models at a glance

    @property
    def read(self) -> str:
        return HOW_TO_READ[self.key]


# ----------------------------------------------------------------------------- figures
def _figure_specs(run: tables.Run, t: dict) -> dict:
    """``{name: (caption, Figure)}`` for every figure the run has the data for."""
    specs = _rain_figures(run, t)
    overall = pd.DataFrame({"model": list(run.results),
                            "ap": [r["headline"]["3d"]["0.7"] for r in run.results.values()]})
    draws = t.get("draws", pd.DataFrame())
    if not draws.empty:  # the spread over training draws, drawn as a vertical range
        overall = overall.merge(draws[["model", "AP3D min", "AP3D max"]].rename(
            columns={"AP3D min": "ap_lo", "AP3D max": "ap_hi"}), on="model", how="left")
    if not t["runtime"].empty:
        pts = overall.merge(t["runtime"][["model", "ort_p50_ms"]], on="model", how="left")
        pts["model"] = pts["model"].map(lambda m: MODEL_LABELS.get(m, m))
        specs["ap_latency"] = ("Overall headline AP against onnxruntime latency per frame (p50, log scale); a vertical "
                               "bar spans the model's training draws when the run has several.",
                               figures.scatter_figure(pts, "ort_p50_ms", "ap", "onnxruntime latency p50 (ms)",
                                                      "AP40 3D @0.7 (%)", "Accuracy vs latency"))
    curves = {n: (r["pr_curve_raw"]["recall"], r["pr_curve_raw"]["precision"]) for n, r in run.results.items()
              if "pr_curve_raw" in r}
    if curves:
        specs["pr_curves"] = ("Precision-recall curves of the headline metric (3D IoU 0.7, all distances, no 2D-height "
                              "filter): precision and recall at each score of a matched detection, down to the "
                              "model's final recall (dotted).", figures.pr_figure(curves, "Precision-recall, 3D @0.7"))
    dist = pd.DataFrame({n: r["distance"]["3d"]["0.7"] for n, r in run.results.items()
                         if "3d" in r.get("distance", {})}).T
    if not dist.empty:
        specs["ap_distance"] = ("AP40 3D @0.7 per ground-truth distance bin (no 2D-height filter).",
                                figures.distance_figure(dist, "AP vs distance"))
    if "n_points_mean" in t["data_by_weather"].columns:
        specs["data"] = ("Points per frame and LiDAR range per weather preset (SOTIF data set).",
                         figures.data_figure(t["data_by_weather"]))
    data_dir = run.run_dir / "data" / "sotif"
    if run.meta is not None and (data_dir / "ImageSets" / "test.txt").is_file():
        thr = {n: _threshold(m) for n, m in run.summary["models"].items()}
        frame = figures.bev_frame(run.run_dir, run.meta, thr)
        if frame is not None:
            specs["bev"] = ("Bird's-eye view of one test frame, the first after the lane change in the rainiest preset, "
                            "one panel per model: points, ground truth (green, the slow car thick), the model's "
                            "detections above its operating threshold (dashed); metres in the LiDAR frame.",
                            figures.bev_figure(frame, list(thr), MODEL_LABELS))
    specs.update(report_pairs.figure_specs(t))
    return {**specs, **report_space.figure_specs(run.summary, t)}


def _rain_figures(run: tables.Run, t: dict) -> dict:
    """The rain story's figure and the two weather heat maps (presets by time of day, then rain rate)."""
    specs = {}
    if not t["rain"].empty:
        specs["rain"] = ("Headline AP40 3D per model in dry, wet and rain (all times of day) and the noon rain grades "
                         "(soft 4.5, mid 18, hard 50 mm/h), at IoU 0.5 (top) and 0.7 (bottom); bars: 95% bootstrap "
                         f"interval over {_resampled(run)}.", rain_figures.rain_figure(t["rain"], MODEL_LABELS))
    matrix = headline_matrix(t["weather_detail"])
    if matrix.empty:
        return specs
    order = rain.preset_order(matrix.index, run.meta)
    matrix = matrix.reindex(order).rename(columns=lambda m: MODEL_LABELS.get(m, m))
    groups = rain.time_groups(order, run.meta)
    facts = rain.preset_facts(run.meta)
    rates = facts["rain_rate_mmh"].to_dict() if not facts.empty else {}
    specs["heatmap"] = ("Headline AP40 3D @0.7 (all distances, no 2D-height filter) per weather preset and model, "
                        "presets grouped by time of day and ordered by rain rate.",
                        rain_figures.ordered_heatmap(matrix, groups, rates, "Headline AP per weather preset"))
    delta = rain.clear_delta(matrix, run.meta)
    if delta.notna().any().any():
        specs["heatmap_delta"] = ("The same AP minus that of the same time of day's clear preset (ClearNoon, "
                                  "ClearSunset, ClearNight), in points: red is a loss, blue a gain.",
                                  rain_figures.delta_heatmap(delta, groups, rates, "AP relative to clear weather"))
    return specs


def _resampled(run: tables.Run) -> str:
    """What the per-group intervals resample: whole scenario instances when the evaluation grouped frames by them."""
    return "scenario instances" if "over instances" in report_space.ci_method(run.results) else "frames"


def _threshold(model: dict) -> float:
    rows = list((model.get("sotif") or {}).values())
    return float(rows[0]["threshold"]) if rows and rows[0].get("threshold") is not None else figures.DEFAULT_THRESHOLD


# ----------------------------------------------------------------------------- display tables
def _ci_display(wide: pd.DataFrame, models: list[str]) -> pd.DataFrame:
    """The main table with each model's value as "AP [lo, hi]"."""
    if wide.empty:
        return wide
    out = wide[["weather"]].copy()
    for m in models:
        if m in wide.columns:
            out[m] = [("–" if pd.isna(v) else f"{v:.1f} [{lo:.1f}, {hi:.1f}]")
                      for v, lo, hi in zip(wide[m], wide[f"{m} lo"], wide[f"{m} hi"])]
    return out


def _group_matrix(long: pd.DataFrame, column: str) -> pd.DataFrame:
    m = headline_matrix(long, column)
    return m.rename_axis(column).reset_index() if not m.empty else m


def _space_section(run: tables.Run, t: dict) -> list[Section]:
    """"SOTIF over the scenario space" (``harness.report_space``), when the run has its results; the lead table
    opens with the boundary rows (``harness.report_bounds``) when the run searched boundaries."""
    if "sotif_instances" not in t:
        return []
    rates = report_space.rate_matrix(t.get("sotif_pass_rates", pd.DataFrame()), t.get("sotif_phantoms"))
    bounds = report_bounds.lead_rows(run.boundaries)
    matrix = report_bounds.with_rows(bounds, rates)
    answer = [Section("sotif_answer", "Where each detector stops finding the slow car in time",
                      report_space.answer_intro(t, bounds=not bounds.empty), [("", matrix, 2)], ["sotif_margins"],
                      lead=True)] if not matrix.empty else []
    return answer + [Section("sotif_space", "SOTIF over the scenario space", report_space.section_intro(run.summary, t),
                             _space_tables(run, t), [*_boundary_names(run, t), "reliability"])]


def _space_tables(run: tables.Run, t: dict) -> list:
    """The section's tables: the boundaries (when the run searched them), pairs, triggering conditions, ECE."""
    bounds = [(report_bounds.caption(run.summary), report_bounds.table(run.boundaries), 2)] \
        if not run.boundaries.empty else []
    return [*bounds,
            ("Model pairs whose verdicts differ (exact McNemar, p < 0.05)",
             _apart(t.get("sotif_pairs", pd.DataFrame())), 3),
            ("Triggering conditions: the swept condition bins with the lowest pass rate",
             t.get("triggering_conditions", pd.DataFrame()), 2),
            ("Expected calibration error per weather class", t.get("calibration", pd.DataFrame()), 3)]


def _apart(pairs: pd.DataFrame) -> pd.DataFrame:
    """The model pairs the McNemar test separates (every pair: tables/sotif_pairs.csv)."""
    return pairs[pairs["apart"]] if not pairs.empty else pairs


def _boundary_names(run: tables.Run, t: dict) -> list[str]:
    b = t.get("sotif_boundary", pd.DataFrame())
    return [f"boundary_{m}" for m in dict.fromkeys(b["model"])] if not b.empty else []


def _sections(run: tables.Run, t: dict) -> list[Section]:
    models = run.models
    c = sotif.constants()
    draws = [Section("draws", "Training draws",
                     "Each model trained with several seeds (`run --seeds K`): mean, lowest and highest over the "
                     "draws, next to the width of the 95% bootstrap interval over frames of draw 0's headline AP "
                     "in its narrowest and widest weather group. The other tables show draw 0.",
                     [("", t["draws"], 1)], [])] if "draws" in t else []
    order = rain.preset_order(t["weather_headline"].get("weather", []), run.meta)
    by_weather = t["weather_headline"].set_index("weather").reindex(order).reset_index() if order else t["weather_headline"]
    relative = t["relative_ap"].set_index("weather").reindex(order).reset_index() if order else t["relative_ap"]
    out = [
        _rain_section(t["rain"], _resampled(run)),
        Section("main", "Headline AP per weather preset",
                "AP40 3D at IoU 0.7 over all distances with the 2D-height filter off, with 95% intervals by "
                f"{report_space.ci_method(run.results)} (the SOTIF targets are far and small, so KITTI's moderate/hard filters would ignore "
                "most of them); presets grouped by time of day, by rain rate within.",
                [("", _ci_display(by_weather, models), 1)], ["heatmap", "heatmap_delta"], figures_first=True,
                notes=tuple(n for n in (notes.lidar_twins_note(run.meta), notes.fog_note(run.meta)) if n)),
        *draws, *[Section(*s) for s in report_pairs.sections(t, run.summary)],
        Section("paper", "KITTI protocol (the paper's tables)",
                "AP11 and AP40 at IoU 0.7 for 2D bbox, BEV, 3D and AOS with KITTI's easy/moderate/hard filters; "
                "recall at the proposals (RoI) and refined boxes (RCNN) for two-stage models.",
                [("AP at IoU 0.7 (%)", t["kitti_ap"], 2), ("Recall of two-stage models (%)", t["recall"], 1)], []),
        # the one-frame view of the study's protocol; a run with the scenario space's verdict shows that instead
        *([] if "sotif_instances" in t else [Section("sotif", "SOTIF view: the slow car after the cut-out",
                f"First detection of the slow car in the ego lane after the fast car's lane change (BEV IoU >= "
                f"{c['iou_bev_min']}, score >= the model's F1-optimal threshold on the val split). Each cell: verdict, "
                "the gap from the ego's front bumper to its rear face left at that moment if the ego had kept its "
                "closing speed dv from the lane change (the simulated ego brakes on ground truth), vs the stopping "
                f"distance dv*{c['t_react_s']:g} s + dv^2/(2*{c['decel_mps2']:g} m/s^2) + {c['margin_m']:g} m, "
                "and the time after the lane change.", [("", t["sotif_matrix"], 1)], [],
                notes=tuple(n for n in (notes.sotif_leniency(t["sotif"]),) if n))]),
        *_space_section(run, t),
        Section("robustness", "Robustness",
                "AP relative to each model's clean value (mean of ClearNoon and ClearSunset); mRR = mean relative "
                "AP over the rain and wet presets (Robo3D), with a 95% interval from the presets' bootstrap intervals "
                "(delta method); the worst preset is the rain or wet preset of lowest relative AP; headline AP by "
                "time of day and precipitation class.",
                [("Summary", rain.robustness_display(t["robustness"]), 2),
                 ("AP relative to clean, per weather", relative, 2),
                 ("By time of day (AP40 3D @0.7)", _group_matrix(t["time_of_day"], "time_of_day"), 1),
                 ("By precipitation class (AP40 3D @0.7)", _group_matrix(t["precipitation_class"],
                                                                         "precipitation_class"), 1)], []),
        Section("detail", "Per weather and model: all numbers",
                "Headline 3D and BEV AP, 95% interval, KITTI moderate AP40, AP per distance bin and RCNN recall. "
                "Cars columns: the Car boxes behind an AP; KITTI's AP40 over n boxes is at most (n - 1) / 40 "
                "(it samples its recall positions among the matches), so 2 boxes cap it at 2.5.",
                [("", t["weather_detail"], 1)], ["ap_distance", "pr_curves"], details=True),
        Section("runtime", "Runtime",
                "onnxruntime latency per frame (p50/p90, timed one model at a time with every core), throughput, "
                "latency p50 during the prediction stage (all test frames, beside another job when the run has "
                "several), ONNX size, parameters, peak resident memory, torch eager vs onnxruntime (speed-up, share "
                "of frames with the same boxes, largest score difference).",
                [("", t["runtime"], 2)], ["ap_latency"]),
        Section("data", "Data",
                "The SOTIF test data per weather preset and one scene per preset.",
                [("", t["data_by_weather"], 1),
                 ("What the weather did to the LiDAR: returns on the slow car (within 65 m) and their share of "
                  "ClearNoon's on the same scenario steps, next to the two-way transmission T^2 the Marshall-Palmer "
                  "model predicts at the car (the share of return power that gets through; a return is lost only "
                  "when T^2 pushes it under the sensor's threshold), returns smeared around the car, and phantom "
                  "returns in the air within 30 m (raindrops, spray, sunlight) per frame.", t["lidar_fidelity"], 2)],
                ["data", "bev"]),
        Section("stages", "Pipeline stages",
                "Seconds per stage, as each job recorded it (stages of parallel model jobs overlap, so they add up "
                "to more than the wall time).", [("", t["stages"], 1)], []),
    ]
    for s in out:
        if s.key in ACCURACY_SECTIONS:
            s.intro = f"{s.intro} {report_pairs.draws_note(run.summary)}"
    return out


def _rain_section(long: pd.DataFrame, resampled: str) -> Section:
    """The report's lead: per model, dry / wet / rain and the rain grades at both IoUs, with their intervals."""
    counts = long.drop_duplicates("condition") if not long.empty else long
    behind = ", ".join(f"{r.condition} {r.n_frames} frames / {r.n_car} cars" for r in counts.itertuples())
    return Section("rain", "Which detectors hold up in rain",
                   f"AP40 3D, all distances, no 2D-height filter, [95% bootstrap interval over {resampled}]. Dry / wet / "
                   "rain: all presets of that class and time of day; soft / mid / hard rain: the noon rain presets "
                   f"(4.5, 18, 50 mm/h). Behind each cell: {behind or 'no groups'}.",
                   [("", rain.rain_display(long), 1)], ["rain"], lead=True)


# ----------------------------------------------------------------------------- rendering
def _overview(run: tables.Run) -> dict:
    s, data = run.summary, run.summary.get("data", {})
    models = [{"name": n, "architecture": m.get("architecture", "?"), "two_stage": bool(m.get("two_stage")),
               "uses_camera": bool(m.get("uses_camera"))} for n, m in s["models"].items()]
    frames = {k: data.get(f"n_{k}_frames") for k in ("test", "val", "train")}
    total = sum(v for v in (s.get("stage_seconds") or {}).values() if isinstance(v, (int, float)))
    vals = notes.val_sets(run.run_dir, s)
    return {"profile": s.get("profile", "?"), "smoke": SMOKE_BANNER if s.get("profile") == "quick" else None,
            "created": s.get("created", "?"), "models": models, "frames": frames, "total_seconds": total or None,
            "wall_seconds": s.get("wall_seconds"), "read": HOW_TO_READ["models"], "vals": vals, "val": _val_set(s), "draws_note": report_pairs.draws_note(s),
            "val_note": notes.val_note(vals), "published": published_note(s), "val_header": notes.val_header(vals), "code": provenance.compare(s.get("code")),
            "machine": provenance.machine_note(s), "data_sets": data_identity.note(run.run_dir), "glossary": _glossary(run.run_dir)}


def _glossary(run_dir: Path) -> str | None:
    """The relative link from the run folder to docs/glossary.md of this checkout, None when there is none."""
    doc = provenance.ROOT / "docs" / "glossary.md"
    return Path(os.path.relpath(doc, run_dir.resolve())).as_posix() if doc.is_file() else None
def _val_set(summary: dict) -> str:
    """What the models table's val column was measured on."""
    val = next((m["val"] for m in summary["models"].values() if isinstance(m.get("val"), dict)), None)
    return f"the val set ({val['data']})" if val and val.get("data") else \
        "held-out dry frames of the training generator (the training set's own val split)"


def _html_table(df: pd.DataFrame, decimals: int) -> Markup:
    if df.empty:
        return Markup("<p class='empty'>(not available in this run)</p>")
    cells = readable(mark_capped(df, decimals)).astype(object)
    cells = cells.map(lambda v: tables.display_cell(v, decimals))  # as in report.md
    html = cells.to_html(index=False, border=0, classes="tbl")  # in a box that scrolls when the table is wider
    html = html.replace("<td>FAIL", '<td class="fail">FAIL').replace("<td>pass", '<td class="pass">pass')
    html = html.replace("<td>fails everywhere", '<td class="fail">fails everywhere')  # report_bounds.cell
    return Markup(f'<div class="tablebox">{html}</div>')


def _render(run: tables.Run, t: dict, figs: dict, md_links: dict) -> tuple[str, str]:
    """(report.md, index.html) text."""
    sections = [s for s in _sections(run, t) if any(not df.empty for _, df, _ in s.tables) or
                any(f in figs for f in s.figures)]
    sections.sort(key=lambda s: s.key != "sotif_answer")  # the SOTIF answer opens the report, above the rain table
    ctx = {"overview": _overview(run), "sections": sections, "captions": {k: v[0] for k, v in figs.items()},
           "models_table": report_pairs.with_draw_ranges(t["overview"], run.summary)}
    env_md = Environment(loader=FileSystemLoader(TEMPLATES), undefined=StrictUndefined, autoescape=False,
                         keep_trailing_newline=True)
    md = env_md.get_template("report.md.j2").render(**ctx, images=md_links,
                                                    md=lambda df, digits: tables.to_markdown(
                                                        readable(mark_capped(df, digits)), digits))
    md = re.sub(r"\n{3,}", "\n\n", md)
    env_html = Environment(loader=FileSystemLoader(TEMPLATES), undefined=StrictUndefined, autoescape=True)
    uris = {k: "data:image/png;base64," + base64.b64encode(v[1]).decode("ascii") for k, v in figs.items()}
    html = env_html.get_template("index.html.j2").render(**ctx, images=uris, table=_html_table)
    return md, html


def render(run_dir) -> Path:
    """Write tables/, figures/, report.md and index.html of a run directory; returns index.html's path."""
    run_dir = Path(run_dir)
    run = tables.load_run(run_dir)
    t = tables.build_tables(run)
    figs = {name: (caption, figures.png(fig)) for name, (caption, fig) in _figure_specs(run, t).items()}
    md, html = _render(run, t, figs, {k: f"figures/{k}.png" for k in figs})
    tables.write_tables(run_dir, t)
    for name, (_, data) in figs.items():
        atomic_write_bytes(run_dir / "figures" / f"{name}.png", data)
    atomic_write_text(run_dir / "report.md", md)
    return atomic_write_text(run_dir / "index.html", html)
