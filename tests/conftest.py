"""Suite-wide settings: the suite runs in two worker processes (pytest-xdist, one test module per
worker at a time); each worker keeps to one intra-op thread so the two do not contend for cores.

The suite's exports share one graph cache (``models.graph_cache``), made by the first process (the
controller, or a lone process without xdist) and handed to the workers through the environment:
a tiny model traced by one test module is read back by the next that exports the same model and
config (entries are written atomically, so two workers tracing one key at once both finish), and
the user's own cache is never touched. ``tests/models/test_export.py`` checks that an export from
the cache gives the bytes of a fresh one."""
import os
import shutil
import tempfile

_SHARED = "SOTIF_TEST_GRAPH_CACHE"  # the suite's graph cache folder, set by the process that made it
_OWN: list[str] = []  # the folder this process made (and removes at the end)


def pytest_configure(config):
    if not os.environ.get(_SHARED):
        _OWN.append(tempfile.mkdtemp(prefix="sotif-test-graphs-"))
        os.environ[_SHARED] = _OWN[0]
    os.environ["SOTIF_BENCH_GRAPH_CACHE"] = os.environ[_SHARED]
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import torch
        torch.set_num_threads(1)


def pytest_unconfigure(config):
    for path in _OWN:
        shutil.rmtree(path, ignore_errors=True)
