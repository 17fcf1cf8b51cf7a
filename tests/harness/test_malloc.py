import subprocess
import sys

import pytest

SCRIPT = """
import resource, sys
import numpy as np
from harness.malloc import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
def step():  # a training step's activations: 16 blocks of 1 MiB written, then all freed
    blocks = [np.ones(1 << 17) for _ in range(16)]
    del blocks
step()  # warm-up: the heap grows once
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    step()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_freed_memory_is_reused_without_page_faults():
    def faults(mode: str) -> int:
        return int(subprocess.run([sys.executable, "-c", SCRIPT, mode], check=True, capture_output=True,
                                  text=True).stdout)
    default, kept = faults("default"), faults("keep")
    assert default > 20 * 2000  # glibc's default: the freed heap top goes back, 16 MiB re-faulted per step
    assert kept < 200
