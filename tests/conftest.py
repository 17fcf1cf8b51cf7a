"""Suite-wide settings: the suite runs in two worker processes (pytest-xdist, one test module per
worker at a time); each worker keeps to one intra-op thread so the two do not contend for cores."""
import os


def pytest_configure(config):
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import torch
        torch.set_num_threads(1)
