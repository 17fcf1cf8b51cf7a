"""benchmarks/bench_nms.py: the fixed-point round count of a suppression chain."""
import torch

from benchmarks.bench_nms import rounds
from models.nms import suppress_fixed_point


def test_rounds_of_a_chain_and_of_no_pairs():
    # 0 suppresses 1, 1 suppresses 2, 2 suppresses 3: greedy keeps 0 and 2
    j, i = torch.tensor([0, 1, 2]), torch.tensor([1, 2, 3])
    assert suppress_fixed_point(j, i, 4).tolist() == [True, False, True, False]
    # all kept -> 1, 2, 3 out -> 2, 3 back (1, 2 are out) -> 3 out again (2 is back) -> unchanged
    assert rounds(j, i, 4) == 4
    none = torch.zeros(0, dtype=torch.int64)
    assert rounds(none, none, 5) == 1
    assert suppress_fixed_point(none, none, 5).all()
