"""Where on an axis each detector's verdict flips: a shared grid refined where any model's outcome flips.

One search covers one reference scenario and one axis (``simulator.bounds``), every model at once, in rounds:

1. *Grid*: ``grid`` values spread evenly over the axis (in log value on a log axis), ends included, probed with
   noise seed 0.
2. *Refine*: for each model, its *bracket* is the first pair of neighbouring probed values, walking from the
   axis's benign end (no rain, the clearest fog, a dry road, the brightest paint), across which its outcome
   flips. Every bracket wider than the axis's tolerance (``Axis.within``) gets its midpoint probed (in log value
   on a log axis), one shared probe where several models' brackets coincide; repeat until every bracket is
   within the tolerance, or for at most ``max_rounds`` rounds.
3. *Seeds*: the final bracket's ends are probed again with the other noise seeds (by default 1 and 2: three in
   all). A model that passes (fails) at every value has its harsh (benign) end probed again instead.

Statuses: ``bracketed`` (to the tolerance), ``bracketed wider than the tolerance (round limit)``, ``passes
everywhere``, ``fails everywhere``, ``no verdict`` (no probe judged the model); after a ``;`` a note when the
model's outcomes flip more than once over the probed values (``not monotone``: the bracket is the flip nearest
the benign end) and when the seeds disagree at an end (``seeds disagree at hi (1 of 3 pass)``). A flip between
two neighbouring probes that both pass (or both fail) is not seen: a grid of n values only sees dips wider
than its step.

An outcome is a bool (passed) or a number, the deceleration needed (a_req, m/s^2; passes at <= ``limit``); None
is no verdict. Pure: ``Search`` holds what was probed and says what to probe next; ``drive`` runs searches
against a batch probe function. Tests: tests/harness/test_boundaries.py.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from simulator.bounds import AXIS_RANGES
from simulator.scenario import A_PASS_MPS2

SEEDS = (0, 1, 2)  # noise seeds: the search's, then the final bracket's reruns
TOLERANCE = {"rain": 5.0, "fog": 0.10, "water": 0.05, "reflectance": 0.05}  # +- absolute; fog: +- 10 %
LOG_AXES = ("fog",)
BENIGN = {"rain": "lo", "fog": "hi", "water": "lo", "reflectance": "hi"}
STATUS_WITHIN, STATUS_WIDE = "bracketed", "bracketed wider than the tolerance (round limit)"
STATUS_PASS, STATUS_FAIL, STATUS_NONE = "passes everywhere", "fails everywhere", "no verdict"
_DIGITS = 6  # significant digits a probed value is rounded to (a value is a probe's name)


@dataclass(frozen=True)
class Axis:
    """An axis to search: its range, unit, tolerance (+-, absolute; on a log axis relative), scale and benign end."""

    name: str
    lo: float
    hi: float
    unit: str
    tol: float
    log: bool = False
    benign: str = "lo"

    def u(self, value: float) -> float:
        return math.log(value) if self.log else float(value)

    def value(self, u: float) -> float:
        v = math.exp(u) if self.log else float(u)
        return float(f"{v:.{_DIGITS}g}")

    def within(self, a: float, b: float) -> bool:
        """The bracket [a, b] places the boundary to +-tol: its width is at most 2 tol (log: b/a <= (1+tol)^2)."""
        half = math.log1p(self.tol) if self.log else self.tol
        return abs(self.u(b) - self.u(a)) <= 2 * half + 1e-9


def axis(name: str) -> Axis:
    """The search axis of ``simulator.bounds``' axis ``name`` with the issue's tolerance."""
    lo, hi, unit = AXIS_RANGES[name]
    return Axis(name, float(lo), float(hi), unit, TOLERANCE[name], name in LOG_AXES, BENIGN[name])


def grid(ax: Axis, n: int) -> list[float]:
    """n >= 2 values evenly spread over the axis (in log value on a log axis), both ends included."""
    if n < 2:
        raise ValueError(f"a grid needs at least its two ends, got {n}")
    a, b = ax.u(ax.lo), ax.u(ax.hi)
    return [ax.value(a + (b - a) * i / (n - 1)) for i in range(n)]


def passed(outcome, limit: float = A_PASS_MPS2) -> bool | None:
    """An outcome as passed / failed / None (no verdict): a bool as it is, a number (a_req) <= limit."""
    if outcome is None or isinstance(outcome, bool):
        return outcome
    return bool(float(outcome) <= limit)


def walk(ax: Axis, outcomes: dict[float, bool | None]) -> list[tuple[float, bool]]:
    """(value, passed) of the judged values from the benign end on."""
    vals = sorted((v for v, p in outcomes.items() if p is not None), reverse=ax.benign == "hi")
    return [(v, outcomes[v]) for v in vals]


def flips(ax: Axis, outcomes: dict[float, bool | None]) -> list[tuple[float, float]]:
    """The neighbouring pairs (lo < hi) across which the outcome changes, from the benign end on."""
    w = walk(ax, outcomes)
    return [tuple(sorted((a[0], b[0]))) for a, b in zip(w, w[1:]) if a[1] != b[1]]


def midpoint(ax: Axis, a: float, b: float) -> float:
    return ax.value((ax.u(a) + ax.u(b)) / 2)


class Search:
    """One reference scenario and axis, every model: what was probed (``results``), what to probe next."""

    def __init__(self, ax: Axis, models, n_grid: int = 3, max_rounds: int | None = None, seeds=SEEDS,
                 limit: float = A_PASS_MPS2):
        self.axis, self.models, self.limit = ax, list(models), limit
        self.grid, self.max_rounds, self.seeds = grid(ax, n_grid), max_rounds, tuple(seeds)
        self.results: dict[tuple[float, int], dict] = {}  # (value, seed) -> {model: passed or None}
        self.rounds = 0  # refinement rounds asked for

    def add(self, value: float, seed: int, outcome: dict) -> None:
        self.results[(float(value), int(seed))] = {m: passed(outcome.get(m), self.limit) for m in self.models}

    def outcomes(self, model: str, seed: int | None = None) -> dict[float, bool | None]:
        seed = self.seeds[0] if seed is None else seed
        return {v: r[model] for (v, s), r in self.results.items() if s == seed}

    def bracket(self, model: str) -> tuple[float, float] | None:
        f = flips(self.axis, self.outcomes(model))
        return f[0] if f else None

    def _refine(self) -> list[float]:
        out = set()
        for m in self.models:
            b = self.bracket(m)
            if b is not None and not self.axis.within(*b):
                out.add(midpoint(self.axis, *b))
        return sorted(v for v in out if (v, self.seeds[0]) not in self.results)

    def _ends(self, model: str) -> list[float]:
        """The values the other seeds probe again for ``model``: its bracket's ends, or the end that tests it."""
        b = self.bracket(model)
        if b is not None:
            return list(b)
        judged = [p for p in self.outcomes(model).values() if p is not None]
        if not judged:
            return []
        benign, harsh = (self.axis.lo, self.axis.hi) if self.axis.benign == "lo" else (self.axis.hi, self.axis.lo)
        return [harsh] if all(judged) else [benign]  # judged alike everywhere: no bracket

    def pending(self) -> list[tuple[float, int]]:
        """(value, seed) pairs of the next round; [] when the search is done. Ask once per round: asking for a
        refinement counts it."""
        first = [(v, self.seeds[0]) for v in self.grid if (v, self.seeds[0]) not in self.results]
        if first:
            return first
        refine = self._refine()
        if refine and (self.max_rounds is None or self.rounds < self.max_rounds):
            self.rounds += 1
            return [(v, self.seeds[0]) for v in refine]
        again = {(v, s) for m in self.models for v in self._ends(m) for s in self.seeds[1:]}
        return sorted(p for p in again if p not in self.results)

    def row(self, model: str) -> dict:
        """``{lo, hi, status, n_probes}`` of one model (module docstring)."""
        ax, out = self.axis, self.outcomes(model)
        judged = [p for p in out.values() if p is not None]
        b = self.bracket(model)
        lo, hi = b if b is not None else (ax.lo, ax.hi)
        if not judged:
            status = STATUS_NONE
        elif b is None:
            status = STATUS_PASS if all(judged) else STATUS_FAIL
        else:
            status = STATUS_WITHIN if ax.within(*b) else STATUS_WIDE
        notes = []
        n_flips = len(flips(ax, out))
        if n_flips > 1:
            notes.append(f"not monotone ({n_flips} flips)")
        for end, v in (("lo", lo), ("hi", hi)):
            seen = [self.results[(v, s)][model] for s in self.seeds if (v, s) in self.results]
            seen = [p for p in seen if p is not None]
            if len(set(seen)) > 1:
                notes.append(f"seeds disagree at {end} ({sum(seen)} of {len(seen)} pass)")
        return {"lo": lo, "hi": hi, "status": "; ".join([status] + notes), "n_probes": len(self.results)}


def drive(searches: list[Search], probe_batch, max_batches: int = 100) -> int:
    """Run ``searches`` to their end: each batch asks ``probe_batch([(search index, value, seed), ...])`` for
    ``{(search index, value, seed): {model: outcome}}``, all searches' next rounds at once. Returns the batches."""
    for n in range(max_batches):
        asks = [(i, v, s) for i, srch in enumerate(searches) for v, s in srch.pending()]
        if not asks:
            return n
        got = probe_batch(asks)
        for i, v, s in asks:
            searches[i].add(v, s, got[(i, v, s)])
    raise RuntimeError(f"boundary searches not done after {max_batches} batches")
