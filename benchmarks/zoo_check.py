"""The zoo's ranking checks, read from one finished ``sotif-bench run`` folder.

Per model: validation AP40 3D moderate (on the run's val set, the README's val column and
``tables/draws.csv``'s; the checkpoint's own ``val_ap`` for a run without one), the test split's
headline 3D AP at IoU 0.7 and its distance bins; for two-stage models the recall at the proposals
(RoI) and at the refined boxes (RCNN) at IoU 0.7, and the AP of the proposals alone (their KITTI
result files, ``predictions/<model>/rois/``, evaluated here) beside the AP of the final boxes. Then
the zoo's ranking checks, each printed as ``pass``/``FAIL`` with its numbers:

- val AP40 3D moderate >= 85 for every model;
- Part-A2, PV-RCNN and PointRCNN at or above SECOND (val AP);
- refined boxes beat proposals: recall @0.7 RCNN > RoI, and final-box AP > proposal AP;
- MVX-Net at or above DV-SECOND (val AP) and within 10 points of it in every distance bin;
- PointRCNN's 0-30 m AP at least its 30-50 m AP.

A run with several training draws (``run --seeds K``) adds, per model, the mean and the range
(min-max) over its draws of the val AP and of the headline, and for every pair of models whether
their ranges are apart: a ranking between two models holds beyond the draws only when the worse
draw of one is above the better draw of the other. The checks above read draw 0.

    python benchmarks/zoo_check.py reports/default [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from harness.cells import DISTANCE_BINS as BINS  # "0-30", "30-50", "50-80" (m)
from harness.tables import mean_range  # the draws table's mean and range

TWO_STAGE = ("parta2", "pv_rcnn", "point_rcnn")


def val_ap(entry: dict) -> float | None:
    """AP40 3D moderate of a model (``results.json`` "models") or a draw ("draws"): on the run's val set
    (``val``) when it has one, else the checkpoint's ``val_ap`` (the training set's val split)."""
    run_val = (entry.get("val") or {}).get("3d_moderate")
    if run_val is not None:
        return run_val
    ckpt = entry.get("val_ap", (entry.get("train") or {}).get("val_ap"))
    return ckpt.get("3d_moderate") if isinstance(ckpt, dict) else ckpt


def _summary(run: Path) -> dict:
    return json.loads((run / "results.json").read_text())


def model_rows(run: Path, summary: dict | None = None) -> dict[str, dict]:
    """One row of figures per model of the run (missing figures are None); ``summary``: its results.json, read
    here when not given."""
    from harness.evaluate import evaluate
    summary = summary or _summary(run)
    test = run / "data" / "sotif" / "ImageSets" / "test.txt"
    rows = {}
    for name, m in summary["models"].items():
        res = json.loads((run / m["results"]).read_text())
        row = {"val_ap": val_ap(m), "ap3d": res["headline"]["3d"]["0.7"],
               **{f"ap3d_{b}m": res["distance"]["3d"]["0.7"].get(b) for b in BINS}}
        rois = run / "predictions" / name / "rois"
        if "roi" in res["recall"]:
            row["recall_roi@0.7"] = 100 * res["recall"]["roi"]["0.7"]
            row["recall_rcnn@0.7"] = 100 * res["recall"]["rcnn"]["0.7"]
        if rois.is_dir():
            roi = evaluate(run / "data" / "sotif", rois, split=test, n_bootstrap=1)
            row["ap3d_proposals"] = roi["headline"]["3d"]["0.7"]
        rows[name] = row
    return rows


def draw_spread(run: Path, summary: dict | None = None) -> dict[str, dict]:
    """Per model of a run with training draws: {"val_ap": [...], "ap3d": [...]} over its draws (draw
    order; None where a figure is missing). Empty for a run of one draw."""
    summary = summary or _summary(run)
    out = {}
    for name, draws in (summary.get("draws") or {}).items():
        out[name] = {"val_ap": [val_ap(d) for d in draws],
                     "ap3d": [(d.get("headline") or {}).get("3d", {}).get("0.7") for d in draws]}
    return out


def separated(spread: dict[str, dict], key: str) -> list[tuple[str, str, bool]]:
    """(better by mean, worse by mean, ranges apart) for every pair of models with ``key`` in every
    draw: apart when the better model's worst draw is above the other's best draw."""
    full = {n: mean_range(v[key]) for n, v in spread.items() if v[key] and None not in v[key]}
    names = sorted(full, key=lambda n: -full[n]["mean"])
    return [(a, b, full[a]["min"] > full[b]["max"]) for i, a in enumerate(names) for b in names[i + 1:]]


def checks(rows: dict[str, dict]) -> list[tuple[str, bool | None, str]]:
    """(check, passed or None when the run lacks a model it needs, the numbers)."""
    out = []
    val = {n: r["val_ap"] for n, r in rows.items()}
    for n, v in val.items():
        out.append((f"{n}: val AP >= 85", None if v is None else v >= 85, f"{v:.1f}" if v is not None else "no val AP"))
    sec = val.get("second")
    for n in TWO_STAGE:
        if n in val:
            ok = None if sec is None or val[n] is None else val[n] >= sec
            out.append((f"{n}: val AP >= SECOND", ok, f"{val[n]:.1f} vs {sec:.1f}" if ok is not None
                        else "no val AP of SECOND" if sec is None else "no val AP"))
    for n in TWO_STAGE:
        r = rows.get(n)
        if r and "recall_roi@0.7" in r:
            out.append((f"{n}: recall@0.7 RCNN > RoI", r["recall_rcnn@0.7"] > r["recall_roi@0.7"],
                        f"{r['recall_rcnn@0.7']:.1f} vs {r['recall_roi@0.7']:.1f}"))
        if r and "ap3d_proposals" in r:
            out.append((f"{n}: final AP > proposal AP", r["ap3d"] > r["ap3d_proposals"],
                        f"{r['ap3d']:.1f} vs {r['ap3d_proposals']:.1f}"))
    mvx, dv = rows.get("mvx_net"), rows.get("dv_second")
    if mvx and dv:
        ok = None if mvx["val_ap"] is None or dv["val_ap"] is None else mvx["val_ap"] >= dv["val_ap"]
        out.append(("mvx_net: val AP >= DV-SECOND", ok, f"{mvx['val_ap']:.1f} vs {dv['val_ap']:.1f}" if ok is not None else ""))
        gaps = {b: dv[f"ap3d_{b}m"] - mvx[f"ap3d_{b}m"] for b in BINS}
        out.append(("mvx_net: within 10 of DV-SECOND in every bin", all(g <= 10 for g in gaps.values()),
                    ", ".join(f"{b} m {mvx[f'ap3d_{b}m']:.1f} vs {dv[f'ap3d_{b}m']:.1f}" for b in BINS)))
    pr = rows.get("point_rcnn")
    if pr:
        out.append(("point_rcnn: 0-30 m AP >= 30-50 m AP", pr["ap3d_0-30m"] >= pr["ap3d_30-50m"],
                    f"{pr['ap3d_0-30m']:.1f} vs {pr['ap3d_30-50m']:.1f}"))
    return out


def _fmt(v) -> str:
    return "" if v is None else f"{v:.1f}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path, help="a finished run folder (holds results.json)")
    p.add_argument("--json", type=Path, help="also write the rows and checks here")
    a = p.parse_args(argv)
    if not (a.run / "results.json").is_file():
        print(f"{a.run}: no results.json (not a finished run folder)", file=sys.stderr)
        return 2
    summary = _summary(a.run)  # a run's results.json is megabytes: read once
    rows = model_rows(a.run, summary)
    on_run_val = all((m.get("val") or {}).get("3d_moderate") is not None for m in summary["models"].values())
    print("val_ap: AP40 3D moderate @0.7 on " + ("the run's val set" if on_run_val else
                                              "each checkpoint's val split (the run has no val set)") + "\n")
    cols = ["val_ap", "ap3d", *(f"ap3d_{b}m" for b in BINS), "ap3d_proposals", "recall_roi@0.7", "recall_rcnn@0.7"]
    print("| model | " + " | ".join(cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    for n, r in rows.items():
        print(f"| {n} | " + " | ".join(_fmt(r.get(c)) for c in cols) + " |")
    print()
    results = checks(rows)
    for name, ok, numbers in results:
        print(f"{'n/a ' if ok is None else 'pass' if ok else 'FAIL'}  {name}: {numbers}")
    spread = draw_spread(a.run, summary)
    pairs = {}
    if spread:
        print("\n| model | draws | val AP mean | val AP range | AP3D @0.7 mean | AP3D @0.7 range |")
        print("|---|---:|---:|---|---:|---|")
        for n, v in spread.items():
            cells = []
            for key in ("val_ap", "ap3d"):
                m = mean_range(v[key])
                cells += ["", ""] if math.isnan(m["mean"]) else [f"{m['mean']:.1f}", f"{m['min']:.1f}-{m['max']:.1f}"]
            print(f"| {n} | {len(v['val_ap'])} | " + " | ".join(cells) + " |")
        for key, label in (("val_ap", "val AP"), ("ap3d", "AP3D @0.7")):
            pairs[key] = separated(spread, key)
            apart = [f"{a} > {b}" for a, b, ok in pairs[key] if ok]
            within = [f"{a} ~ {b}" for a, b, ok in pairs[key] if not ok]
            print(f"\n{label}, rankings beyond the draws: {', '.join(apart) or 'none'}")
            print(f"{label}, within the draws (no ranking): {', '.join(within) or 'none'}")
    if a.json:
        a.json.write_text(json.dumps({"rows": rows, "checks": [{"check": c, "pass": ok, "numbers": s}
                                                               for c, ok, s in results],
                                      "draws": spread, "separated": pairs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
