"""Shared fixtures of the model tests."""
import pytest
import torch


@pytest.fixture
def one_thread():
    """Tiny tensors on a shared 2-core machine: one intra-op thread avoids contention.

    Modules opt in with ``pytestmark = pytest.mark.usefixtures("one_thread")``."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
