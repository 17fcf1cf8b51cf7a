"""Standard normal draws inside numba kernels: Marsaglia & Tsang's ziggurat (J. Stat. Softw. 5(8), 2000).

256 layers of equal area V under f(x) = exp(-x^2 / 2), the base layer carrying the tail beyond
R. One raw 64-bit word per draw on the fast path (~98.5 %): bits 0-7 pick the layer, bit 8 the
sign, bits 11-63 the uniform; a wedge or tail draw takes one or two more words. The words come
from the caller's numpy Generator (`rng.bit_generator.random_raw`), so a seed still fixes the
bytes, and a kernel draws only as many normals as it needs (e.g. one per detected return)
without numpy's per-call overhead.
"""
from __future__ import annotations

import math

import numba
import numpy as np

ZIG_R = 3.6541528853610088  # start of the tail
ZIG_V = 4.92867323399e-3  # area of each layer


def ziggurat_tables() -> tuple[np.ndarray, np.ndarray]:
    """Layer edges x (257,) (x[0] = V / f(R) is the base layer's virtual width, x[1] = R, x[256] = 0)
    and f(x) (257,): layer i is [0, x[i]) x [f(x[i]), f(x[i + 1])]."""
    x = np.zeros(257)
    x[0], x[1] = ZIG_V / math.exp(-0.5 * ZIG_R * ZIG_R), ZIG_R
    for i in range(1, 255):
        x[i + 1] = math.sqrt(-2.0 * math.log(ZIG_V / x[i] + math.exp(-0.5 * x[i] * x[i])))
    return x, np.exp(-0.5 * x * x)


ZIG_X, ZIG_F = ziggurat_tables()
TO_UNIT = 1.0 / 9007199254740992.0  # 2^-53


@numba.njit(cache=True, inline="always", error_model="numpy")
def _unit(word):
    """Uniform in [0, 1) from the top 53 bits of a raw word."""
    return float(word >> np.uint64(11)) * TO_UNIT


@numba.njit(cache=True, error_model="numpy")
def _layer_draw(raw, pos, w, xs, fs):
    """The full ziggurat step from word w (already taken), retrying with fresh words on a rejection:
    (value, next pos), pos -1 when raw ran out."""
    n = raw.shape[0]
    while True:
        i = int(w & np.uint64(0xFF))
        sign = 1.0 - 2.0 * float((w >> np.uint64(8)) & np.uint64(1))
        x = _unit(w) * xs[i]
        if x < xs[i + 1]:
            return sign * x, pos
        if i == 0:  # tail beyond R (Marsaglia 1964)
            while pos + 1 < n:
                a = -np.log1p(-_unit(raw[pos])) / xs[1]
                b = -np.log1p(-_unit(raw[pos + 1]))
                pos += 2
                if b + b > a * a:
                    return sign * (xs[1] + a), pos
            return 0.0, -1
        if pos >= n:
            return 0.0, -1
        u = _unit(raw[pos])
        pos += 1
        if fs[i] + u * (fs[i + 1] - fs[i]) < np.exp(-0.5 * x * x):  # under the curve in the wedge
            return sign * x, pos
        if pos >= n:
            return 0.0, -1
        w = raw[pos]
        pos += 1


@numba.njit(cache=True, error_model="numpy")
def standard_normals(raw, m, xs, fs):
    """m N(0, 1) draws from the raw words with tables (xs, fs): (values (m,), words used), words
    used -1 when raw ran out. The fast path stays in the loop with a branch-free sign (a sign
    branch or an inlined helper returning tuples makes this loop ~8x slower)."""
    n = raw.shape[0]
    out = np.zeros(m)
    pos = 0
    for k in range(m):
        if pos >= n:
            return out, -1
        w = raw[pos]
        pos += 1
        i = int(w & np.uint64(0xFF))
        x = _unit(w) * xs[i]
        if x < xs[i + 1]:
            out[k] = x * (1.0 - 2.0 * float((w >> np.uint64(8)) & np.uint64(1)))
        else:
            out[k], pos = _layer_draw(raw, pos, w, xs, fs)
            if pos < 0:
                return out, -1
    return out, pos


def normals(rng: np.random.Generator, m: int) -> np.ndarray:
    """m N(0, 1) draws taken from rng's raw words (deterministic for a given rng state)."""
    raw = raw_words(rng, m)
    z, used = standard_normals(raw, m, ZIG_X, ZIG_F)
    while used < 0:  # never seen in practice: take more words and draw again from the same ones
        raw = np.concatenate([raw, rng.bit_generator.random_raw(len(raw))])
        z, used = standard_normals(raw, m, ZIG_X, ZIG_F)
    return z


def raw_words(rng: np.random.Generator, n: int) -> np.ndarray:
    """Enough raw words for n draws with overwhelming probability (~1.5 % of draws take extra words)."""
    return rng.bit_generator.random_raw(n + n // 8 + 64)
