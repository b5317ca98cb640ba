"""
The CNN's correlation on the CPU: numba kernels over the raw descriptors of strips of rows.

Vol(y, x, d) = <f_L(y, x), f_R(y, x - d)>, each descriptor L2-normalized (divided by
max(its norm, EPS), as F.normalize does), the dot product capped at 1 (rounding may overshoot
by an ulp), 0 where x - d < 0. `best_match` streams it, keeping the best disparities of both
views; `volume` writes it (for `cnn.filter`), with the right view's. Both take the cells
of each row from `_two_columns`, so they give the same bits. The descriptors come as
`bits`: (2, rows, W, C) float32 bit patterns, as uint32 (`shift` 0) or as the upper halves
of bfloat16 values in uint16 (`shift` 16), so both widen exactly.
"""
from typing import Any

from numba import int32, njit, prange
import numpy as np

EPS = 1e-8


@njit(inline='always', fastmath=True)
def _unit_rows(bits: np.ndarray, shift: int, y: int) -> np.ndarray:
    """Return rows y of both descriptor images as float32 (2, W, C), L2-normalized."""
    _, _, w, c = bits.shape
    out = np.empty((2, w, c), np.float32)
    out_bits = out.view(np.uint32)
    for i in range(2):
        for x in range(w):
            s = np.float32(0.0)
            for k in range(c):
                out_bits[i, x, k] = np.uint32(bits[i, y, x, k]) << shift
                s += out[i, x, k] * out[i, x, k]
            inv = np.float32(1.0) / max(np.sqrt(s), np.float32(EPS))
            for k in range(c):
                out[i, x, k] *= inv
    return out


@njit(inline='always', fastmath=True)
def _two_columns(f: np.ndarray, x: int, out: np.ndarray, i: int) -> None:
    """
    Write Vol(x, d) into out[i, d] and Vol(x + 1, d) into out[i + 1, d], d < D.

    `f`: the unit rows (2, W, C); with x + 1 = W only out[i]. (x, d) and (x + 1, d + 1)
    read the same right descriptor, loaded once for both (the same bits as one cell at a
    time; the speed: doc/speed.md).
    """
    nd, c, w = out.shape[1], f.shape[2], f.shape[1]
    x1 = min(x + 1, w - 1)
    for d in range(min(nd, x + 1)):
        s0 = s1 = np.float32(0.0)
        for k in range(c):
            r = f[1, x - d, k]
            s0 += f[0, x, k] * r
            s1 += f[0, x1, k] * r
        out[i, d] = min(s0, np.float32(1.0))
        if d + 1 < nd and x1 > x:
            out[i + 1, d + 1] = min(s1, np.float32(1.0))
    for d in range(x + 1, nd):
        out[i, d] = 0
    if x1 > x:
        s = np.float32(0.0)
        for k in range(c):
            s += f[0, x1, k] * f[1, x1, k]
        out[i + 1, 0] = min(s, np.float32(1.0))
        for d in range(x1 + 1, nd):
            out[i + 1, d] = 0


@njit(inline='always', fastmath=True)
def order(bits: Any) -> Any:
    """Return an int32 that orders as the float32 whose bits (as int32) are `bits`."""
    return int32(bits ^ int32(int32(bits >> int32(31)) & int32(0x7fffffff)))


@njit(inline='always', fastmath=True)
def first_argmax(keys: np.ndarray, i: int, n: int) -> Any:
    """
    Return the first argmax over d < n of the float32 values whose bits keys[i] are.

    `keys`: a float32 (rows, D) array viewed as int32. The maximum is taken on `order` of
    the bits: LLVM vectorizes an int32 reduction, not a float one.
    """
    best = int32(-2147483648)
    for d in range(n):
        best = max(best, order(keys[i, d]))
    arg = int32(n)
    for d in range(n):
        arg = min(arg, int32(d) if order(keys[i, d]) == best else int32(n))
    return arg


@njit(inline='always', fastmath=True)
def _right_view(vals: np.ndarray, i: int, n: int, x: int, right_best: np.ndarray,
                right_arg: np.ndarray) -> None:
    """
    Fold Vol(y, x, d) = vals[i, d], d < n, into the right view's first max and argmax.

    Both are stored reversed, at w - 1 - xr: for one x, the right pixels x - d, d = 0, 1,
    ..., are then a forward run, which vectorizes; x, so d, grows for a fixed x - d.
    """
    run = np.uint64(right_best.shape[0] - 1 - x)
    for d in range(n):
        if vals[i, d] > right_best[run + np.uint64(d)]:
            right_best[run + np.uint64(d)] = vals[i, d]
            right_arg[run + np.uint64(d)] = d


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def best_match(bits: np.ndarray, shift: int, max_disp: int, cof_c: np.ndarray, cof_d: np.ndarray,
               cof_dr: np.ndarray) -> None:
    """
    Stream max / first argmax over d of Vol(y, x, d) into (rows, W) cof_c and cof_d.

    And into cof_dr, for each right pixel xr, the first argmax over d < min(D, W - xr) of
    Vol(y, xr + d, d).
    """
    _, h, w, _ = bits.shape
    for y in prange(h):
        f = _unit_rows(bits, shift, y)
        vals = np.empty((2, max_disp), np.float32)
        keys = vals.view(np.int32)
        right_best = np.full(w, np.float32(-1.0))  # below every cosine
        right_arg = np.zeros(w, np.int32)
        for x in range(0, w, 2):
            _two_columns(f, x, vals, 0)
            for i in range(min(2, w - x)):
                n = min(max_disp, x + i + 1)
                arg = first_argmax(keys, i, n)
                cof_c[y, x + i] = vals[i, arg]
                cof_d[y, x + i] = arg
                _right_view(vals, i, n, x + i, right_best, right_arg)
        for x in range(w):
            cof_dr[y, x] = right_arg[w - 1 - x]


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def volume(bits: np.ndarray, shift: int, vol: np.ndarray, first: int, cof_dr: np.ndarray) -> None:
    """
    Write the volume's rows into `vol` (N, W, D), row y at (first + y) % N, and cof_dr.

    cof_dr (rows, W) as `best_match` writes it.
    """
    _, h, w, _ = bits.shape
    for y in prange(h):
        f = _unit_rows(bits, shift, y)
        row = vol[(first + y) % vol.shape[0]]
        right_best = np.full(w, np.float32(-1.0))
        right_arg = np.zeros(w, np.int32)
        for x in range(0, w, 2):
            _two_columns(f, x, row, x)
            for i in range(min(2, w - x)):
                _right_view(row, x + i, min(vol.shape[2], x + i + 1), x + i, right_best,
                            right_arg)
        for x in range(w):
            cof_dr[y, x] = right_arg[w - 1 - x]
