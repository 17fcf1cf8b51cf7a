"""The boundary search against synthetic probes whose thresholds are known, every probe worked by hand."""
import math

import pytest

from harness.boundaries import (STATUS_FAIL, STATUS_NONE, STATUS_PASS, STATUS_WIDE, STATUS_WITHIN, Search, axis,
                                drive, flips, grid, passed)


def run(search: Search, probe) -> list[list[tuple[float, int]]]:
    """Drive one search with ``probe(value, seed) -> {model: outcome}``; returns the rounds' probes."""
    rounds = []

    def batch(asks):
        rounds.append([(v, s) for _, v, s in asks])
        return {(i, v, s): probe(v, s) for i, v, s in asks}
    drive([search], batch)
    return rounds


def test_axes_and_grids():
    rain, fog = axis("rain"), axis("fog")
    assert (rain.lo, rain.hi, rain.unit, rain.tol, rain.benign) == (0.0, 100.0, "mm/h", 5.0, "lo")
    assert grid(rain, 3) == [0.0, 50.0, 100.0]
    assert grid(fog, 3) == [50.0, 316.228, 2000.0]  # sqrt(50 * 2000)
    assert rain.within(31.25, 37.5) and not rain.within(25.0, 37.5)  # 6.25 <= 10 < 12.5
    assert fog.within(100.0, 121.0) and not fog.within(100.0, 121.5)  # 1.1^2 = 1.21
    assert axis("reflectance").benign == "hi" and axis("water").tol == 0.05
    with pytest.raises(ValueError):
        grid(rain, 1)


def test_outcomes_as_a_req():
    assert passed(6.0) is True and passed(6.01) is False and passed(math.inf) is False
    assert passed(True) is True and passed(None) is None


def test_two_monotone_models_on_rain():
    """A fails above 37 mm/h, B above 81. Grid 0 50 100: A P F F, B P P F. Round 1: A's (0, 50) -> 25, B's
    (50, 100) -> 75. Round 2: A (25, 50) -> 37.5 (fails), B (75, 100) -> 87.5 (fails). Round 3: A (25, 37.5),
    12.5 wide -> 31.25 (passes); B (75, 87.5) -> 81.25 (fails). Now A (31.25, 37.5) and B (75, 81.25) are 6.25
    <= 10 wide. Seeds 1 and 2 at the four ends: 8 probes. 9 + 8 = 17."""
    thresholds = {"A": 37.0, "B": 81.0}
    s = Search(axis("rain"), thresholds)
    rounds = run(s, lambda v, seed: {m: v <= t for m, t in thresholds.items()})
    assert [sorted(v for v, _ in r) for r in rounds[:4]] == [[0.0, 50.0, 100.0], [25.0, 75.0], [37.5, 87.5],
                                                            [31.25, 81.25]]
    assert sorted(rounds[4]) == [(v, seed) for v in (31.25, 37.5, 75.0, 81.25) for seed in (1, 2)]
    assert len(rounds) == 5 and s.row("A")["n_probes"] == 17
    assert s.row("A") == {"lo": 31.25, "hi": 37.5, "status": STATUS_WITHIN, "n_probes": 17}
    assert s.row("B") == {"lo": 75.0, "hi": 81.25, "status": STATUS_WITHIN, "n_probes": 17}


def test_shared_probes_when_brackets_coincide():
    """A fails above 60, B above 62: the same midpoints serve both. Grid 0 50 100; 75 (F both); 62.5 (F both);
    56.25 (P both): (56.25, 62.5) 6.25 wide. 3 + 3 refinements + 2 ends x 2 seeds = 10 probes."""
    s = Search(axis("rain"), ["A", "B"])
    run(s, lambda v, seed: {"A": v <= 60, "B": v <= 62})
    assert s.row("A") == s.row("B") == {"lo": 56.25, "hi": 62.5, "status": STATUS_WITHIN, "n_probes": 10}


def test_fog_on_a_log_axis_from_the_benign_end():
    """Fails in fog thinner than 120 m MOR. Grid 50 316.228 2000 (F P P); geometric midpoints of the (rounded)
    ends: sqrt(50 x 316.228) = 125.743 (P), sqrt(50 x 125.743) = 79.2916 (F), 99.8517 (F), 112.052 (F):
    125.743 / 112.052 = 1.122 <= 1.21. 7 probes + 2 ends x 2 seeds = 11."""
    s = Search(axis("fog"), ["A"])
    rounds = run(s, lambda v, seed: {"A": v >= 120.0})
    assert [r[0][0] for r in rounds[1:5]] == [125.743, 79.2916, 99.8517, 112.052]
    assert s.row("A") == {"lo": 112.052, "hi": 125.743, "status": STATUS_WITHIN, "n_probes": 11}


def test_a_req_outcomes_and_everywhere_statuses():
    """Reflectance, benign end 0.8: A needs 4 m/s^2 everywhere (passes), B 9 m/s^2 (fails). Grid 0.02 0.41 0.8;
    no flip; seeds 1 and 2 probe A's harsh end 0.02 and B's benign end 0.8: 3 + 4 = 7 probes."""
    s = Search(axis("reflectance"), ["A", "B"])
    rounds = run(s, lambda v, seed: {"A": 4.0, "B": 9.0})
    assert sorted(rounds[1]) == [(0.02, 1), (0.02, 2), (0.8, 1), (0.8, 2)]
    assert s.row("A") == {"lo": 0.02, "hi": 0.8, "status": STATUS_PASS, "n_probes": 7}
    assert s.row("B")["status"] == STATUS_FAIL


def test_non_monotone_takes_the_flip_nearest_the_benign_end():
    """Passes below 30 and above 60 mm/h. Grid 0 50 100: P F P (2 flips). The first from 0: (0, 50) -> 25 (P),
    37.5 (F), 31.25 (F): (25, 31.25); then seeds at both ends."""
    s = Search(axis("rain"), ["A"])
    run(s, lambda v, seed: {"A": v < 30 or v > 60})
    row = s.row("A")
    assert (row["lo"], row["hi"]) == (25.0, 31.25)
    assert row["status"] == f"{STATUS_WITHIN}; not monotone (2 flips)"
    assert flips(s.axis, s.outcomes("A")) == [(25.0, 31.25), (50.0, 100.0)]


def test_seeds_that_disagree_are_named():
    """Water: fails above 0.3 with seed 0, above 0.2 with seed 1, above 0.35 with seed 2. Grid 0 0.5 1 (P F F);
    0.25 (P), 0.375 (F), 0.3125 (F): (0.25, 0.3125) 0.0625 <= 0.1. Seed 1 fails at 0.25, seed 2 passes at
    0.3125."""
    limit = {0: 0.3, 1: 0.2, 2: 0.35}
    s = Search(axis("water"), ["A"])
    run(s, lambda v, seed: {"A": v <= limit[seed]})
    row = s.row("A")
    assert (row["lo"], row["hi"]) == (0.25, 0.3125)
    assert row["status"] == f"{STATUS_WITHIN}; seeds disagree at lo (2 of 3 pass); seeds disagree at hi (1 of 3 pass)"


def test_round_limit_and_no_verdict():
    """One refinement round only: rain A fails above 37: grid, 25 (P); bracket (25, 50) stays 25 wide."""
    s = Search(axis("rain"), ["A", "C"], max_rounds=1, seeds=(0,))
    rounds = run(s, lambda v, seed: {"A": v <= 37, "C": None})
    assert len(rounds) == 2
    assert s.row("A") == {"lo": 25.0, "hi": 50.0, "status": STATUS_WIDE, "n_probes": 4}
    assert s.row("C")["status"] == STATUS_NONE


def test_drive_batches_searches_together():
    """Two searches' rounds go out as one batch each time; the batch count is the longest search's rounds."""
    a, b = Search(axis("rain"), ["A"], seeds=(0,)), Search(axis("water"), ["A"], seeds=(0,))
    sizes = []

    def batch(asks):
        sizes.append(len(asks))
        return {(i, v, s): {"A": v <= (37 if i == 0 else 0.9)} for i, v, s in asks}
    assert drive([a, b], batch) == 4
    assert sizes == [6, 2, 2, 2]  # 3 refinements each: rain 25 37.5 31.25, water (0.5, 1) -> 0.75 0.875 0.9375
