"""The export optimiser with and without the onnxscript rewrite rules it skips (models.export.SKIPPED_REWRITE_RULES):
for each model, its graph traced once (random weights, seed 0; from the graph cache when it holds it), then
optimised both ways: the seconds of each and whether the bytes are the same.

    python -m benchmarks.export_optimiser --profile compact [--models a,b]
"""
from __future__ import annotations

import argparse
import time

import torch

from models import graph_cache, zoo
from models.export import OPSET, SKIPPED_REWRITE_RULES, example_inputs, optimise_graph, trace_graph


def compare(name: str, profile: str) -> dict:
    torch.manual_seed(0)
    net = zoo.build(name, profile).eval()
    traced = graph_cache.load(graph_cache.cache_key(net, OPSET), net)
    source = "cache"
    if traced is None:
        source, traced = "traced", trace_graph(net, example_inputs(net))
    times, out = {}, {}
    for label, skip in (("all rules", ()), ("skipped", SKIPPED_REWRITE_RULES)):
        t0 = time.perf_counter()
        out[label] = optimise_graph(traced, name, skip=skip).SerializeToString()
        times[label] = time.perf_counter() - t0
    return {"model": name, "graph": source, "nodes": len(traced.graph.node), "all rules s": times["all rules"],
            "skipped s": times["skipped"], "same bytes": out["all rules"] == out["skipped"]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--profile", default="compact", choices=zoo.PROFILES)
    p.add_argument("--models", default=",".join(zoo.MODEL_NAMES))
    a = p.parse_args()
    torch.set_num_threads(1)
    print(f"skipped rules: {', '.join(SKIPPED_REWRITE_RULES)}; profile {a.profile}; one thread")
    print(f"{'model':14s} {'graph':7s} {'nodes':>6s} {'all rules s':>12s} {'skipped s':>10s}  same bytes", flush=True)
    for name in a.models.split(","):
        r = compare(name, a.profile)
        print(f"{r['model']:14s} {r['graph']:7s} {r['nodes']:6d} {r['all rules s']:12.1f} {r['skipped s']:10.1f}  "
              f"{r['same bytes']}", flush=True)


if __name__ == "__main__":
    main()
