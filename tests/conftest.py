"""Suite-wide settings: the suite runs in two worker processes (pytest-xdist, one test module per
worker at a time); each worker keeps to one intra-op thread so the two do not contend for cores."""
import os
import shutil
import tempfile

_GRAPHS = tempfile.mkdtemp(prefix="sotif-test-graphs-")


def pytest_configure(config):
    os.environ["SOTIF_BENCH_GRAPH_CACHE"] = _GRAPHS  # the suite's exports never touch the user's graph cache
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import torch
        torch.set_num_threads(1)


def pytest_unconfigure(config):
    shutil.rmtree(_GRAPHS, ignore_errors=True)
