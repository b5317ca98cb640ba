"""
Semi-global matching (Hirschmueller 2008) on a cost volume (H, W, D).

Path cost along direction r = (dx, dy), with p - r the previous pixel on the path:
    L_r(p, d) = C(p, d) + min(L_r(p-r, d), L_r(p-r, d+-1) + P1, min_k L_r(p-r, k) + P2)
                - min_k L_r(p-r, k)
and L_r(p, d) = C(p, d) where p - r lies outside the image. S = sum over paths; the
disparity is argmin_d S (first minimum on ties).

Paths: 4 (horizontal, vertical), 8 (+ diagonals), 16 (+ the 8 knight moves (+-1, +-2),
(+-2, +-1), the paper's default). The image is swept twice: every path coming from above in
one top-down sweep and every path from below in one bottom-up sweep, the previous two rows of
each path kept in a ring buffer. Each row is one parallel step: each thread's task walks its
band of columns, and in the top-down sweep two of the tasks also walk the two horizontal
paths of the next row, which S adds up first. C is read and S written once per sweep.

Two number types, same code: float32, and uint16 for integer costs (Census distances,
integer penalties). uint16 is exact and halves the memory traffic, which bounds the sweeps;
it needs paths * (max C + P2) <= 65535, since L_r <= C + P2 and S sums `paths` of them.
"""
from collections.abc import Callable
from typing import Any

from llvmlite import ir
import numba
from numba import njit, prange, types
from numba.extending import intrinsic, overload
import numpy as np
import numpy.typing as npt

from .cancel import CancelFlag, flag_array
from .cost import output_array, UINT16_MAX

PATHS = (4, 8, 16)


def directions(paths: int) -> list[tuple[int, int]]:
    """
    Return the (dx, dy) path directions with dy >= 0.

    These are the paths from above or along the row; the sweeps add the mirrored ones.
    Raises ValueError unless `paths` is 4, 8 or 16.
    """
    if paths not in PATHS:
        raise ValueError(f'paths must be one of {PATHS}, got {paths!r}')
    dirs = [(1, 0), (0, 1)]
    if paths >= 8:
        dirs += [(1, 1), (-1, 1)]
    if paths == 16:
        dirs += [(1, 2), (-1, 2), (2, 1), (-2, 1)]
    return dirs


def summation_order(paths: int) -> list[tuple[int, int]]:
    """
    Return all `paths` directions (dx, dy), in the order S adds up their L_r in each cell.

    The two horizontal paths, those from above as `directions` lists them, then their
    opposites: the order of the sweeps below, which the CUDA twin keeps.
    """
    above = [d for d in directions(paths) if d[1] > 0]
    return [(1, 0), (-1, 0)] + above + [(-dx, -dy) for dx, dy in above]


def path_sum_bound(paths: int, max_cost: float, p2: float) -> float:
    """Return the largest value S can take: each path's L_r <= C + P2."""
    return paths * (max_cost + p2)


def _keys(v: np.ndarray) -> np.ndarray:
    """
    Return v as an array that orders like it and whose min reduction vectorizes.

    That is the int32 bits of non-negative float32 values (LLVM leaves a float min reduction
    scalar), else v.
    """
    raise NotImplementedError('for numba-compiled code only')


# numba compares the parameters of an overload with those of the function it returns,
# annotations included: the lambdas have none, so neither have the overloads' parameters.
@overload(_keys, inline='always')
def _keys_impl(v) -> Callable[[np.ndarray], np.ndarray]:  # type: ignore[no-untyped-def]
    if v.dtype == types.float32:
        return lambda v: v.view(np.int32)
    return lambda v: v


# numba's stub types a call of an intrinsic with the typing context as its first argument:
# the kernels' calls of these two ignore call-arg.
@intrinsic
def _key(typingctx: Any, v: Any) -> tuple[Any, Callable[..., Any]]:
    """Return the key (see `_keys`) of one value: its int32 bits for float32, else v."""
    if v == types.float32:
        return types.int32(v), lambda context, builder, sig, args: builder.bitcast(
            args[0], ir.IntType(32))
    return v(v), lambda context, builder, sig, args: args[0]


@intrinsic
def _key_value(typingctx: Any, k: Any) -> tuple[Any, Callable[..., Any]]:
    """Return the value of a key (see `_key`) as float32: a float32's int32 bits, else k."""
    def bits(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        return builder.bitcast(args[0], ir.FloatType())

    def count(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        return builder.uitofp(args[0], ir.FloatType())

    return types.float32(k), bits if k == types.int32 else count


def _top_key(total: np.ndarray) -> np.integer:
    """Return a key (see `_keys`) no value of the array `total` exceeds: inf's or 65535."""
    raise NotImplementedError('for numba-compiled code only')


@overload(_top_key, inline='always')
def _top_key_impl(total) -> Callable[[np.ndarray], np.integer]:  # type: ignore[no-untyped-def]
    if total.dtype == types.float32:
        return lambda total: np.int32(0x7F800000)  # the bits of +inf
    return lambda total: np.uint16(UINT16_MAX)  # uint16 volumes, the only other type


def _as(like: np.ndarray, x: Any) -> Any:
    """Return x converted to the element type of the array `like`."""
    raise NotImplementedError('for numba-compiled code only')


@overload(_as, inline='always')
def _as_impl(like, x) -> Callable[[np.ndarray, Any], Any]:  # type: ignore[no-untyped-def]
    dtype = like.dtype
    return lambda like, x: dtype(x)


@njit(inline='always', fastmath=True)
def _min_key(v: np.ndarray) -> Any:
    """Return the key (see `_keys`) of min(v), v >= 0."""
    keys = _keys(v)
    m = keys[0]
    for d in range(1, keys.shape[0]):
        b = keys[d]
        m = b if b < m else m
    return m


@njit(inline='always', fastmath=True)
def _path_start(cost: np.ndarray, y: int, x: int, lr: np.ndarray, min_keys: np.ndarray, cur: int,
                total: np.ndarray, add: bool) -> None:
    """Set row `cur` of lr to L_r(p, .) = C(p, .) (p - r outside the image); if add, S += it."""
    m: Any = _key(cost[y, x, 0])  # type: ignore[call-arg]
    for d in range(cost.shape[2]):
        v = cost[y, x, d]
        lr[cur, d + 1] = v
        if add:
            total[y, x, d] = _as(total, total[y, x, d] + v)
        m = min(m, _key(v))
    min_keys[cur] = m


@njit(inline='always', fastmath=True)
def _path_step(cost: np.ndarray, y: int, x: int, lr: np.ndarray, mins: np.ndarray,
               min_keys: np.ndarray, prev: int, cur: int, p1: Any, p2: Any, total: np.ndarray,
               add: bool) -> None:
    """
    Set row `cur` of lr to L_r(p, .) from C(p, .) = cost[y, x] and row `prev`, L_r(p - r, .).

    If add, also S(p, .) = total[y, x] += L_r(p, .). Rows of lr hold L_r(d) at d + 1 and a
    sentinel at both ends (see `_sentinel`), so every d takes the same branch-free step;
    mins (min_keys, its keys) hold each row's min_d. Each value is cast back to the volume's
    type, so uint16 math stays 16 bits wide. Arrays are indexed, never sliced, in the hot
    loops: a view costs two atomic reference counts.
    """
    prev_min = mins[prev]
    jump = _as(lr, prev_min + p2)
    m: Any = _key(lr[prev, 0])  # type: ignore[call-arg]  # the sentinel, above every L_r
    for d in range(cost.shape[2]):
        step = _as(lr, min(lr[prev, d], lr[prev, d + 2]) + p1)
        v = _as(lr, cost[y, x, d] + min(min(lr[prev, d + 1], step), jump) - prev_min)
        lr[cur, d + 1] = v
        if add:
            total[y, x, d] = _as(total, total[y, x, d] + v)
        m = min(m, _key(v))
    min_keys[cur] = m


def _sentinel(dtype: np.dtype, p1: Any) -> np.generic:
    """
    Return the value of the cells at d = -1 and d = D of each path cost row.

    It never wins min(L(d), L(d +- 1) + P1, min L + P2): it plus P1 is the type's largest
    value, at least min L + P2 (path_sum_bound for uint16), and stays finite for float32.
    """
    top = np.iinfo(dtype).max if dtype == np.uint16 else np.finfo(dtype).max
    return dtype.type(top - p1)


@njit(inline='always', fastmath=True)
def _horizontal_row(cost: np.ndarray, y: int, p1: Any, p2: Any, lr: np.ndarray, mins: np.ndarray,
                    min_keys: np.ndarray, row0: int, backward: bool, total: np.ndarray) -> None:
    """Set rows row0 + x of lr to L_r(x, .) along row y, r = (-1, 0) if backward else (1, 0)."""
    w = cost.shape[1]
    x0 = w - 1 if backward else 0
    _path_start(cost, y, x0, lr, min_keys, row0 + x0, total, False)
    for i in range(1, w):
        x = w - 1 - i if backward else i
        prev = x + 1 if backward else x - 1
        _path_step(cost, y, x, lr, mins, min_keys, row0 + prev, row0 + x, p1, p2, total, False)


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def _sweep(cost: np.ndarray, p1: Any, p2: Any, total: np.ndarray, dirs: np.ndarray, down: bool,
           bands: np.ndarray, sentinel: Any, cancel: np.ndarray) -> None:
    """
    Accumulate L_r into total for each r in dirs; dy > 0 counts rows back in sweep order.

    The top-down sweep (`down`) first sets total = L_(1,0) + L_(-1,0): tasks 0 and 1 compute
    those two paths of the next row while every task walks its band of columns
    bands[t]:bands[t + 1] of this row, so each row is one parallel step.
    """
    h, w, nd = cost.shape
    ndirs = dirs.shape[0]
    # Rows of L_r: (direction k, sweep row % 3, x) at (3 k + row % 3) w + x, then those of
    # L_(+-1,0), (path, image row % 2, x), from 3 ndirs w on.
    lr = np.full(((3 * ndirs + 4) * w, nd + 2), sentinel, cost.dtype)
    mins = np.empty(lr.shape[0], cost.dtype)
    min_keys = _keys(mins)
    hrows = 3 * ndirs * w
    for i in range(-1 if down else 0, h):
        if cancel[0]:
            return
        y = i if down else h - 1 - i
        for t in prange(bands.shape[0] - 1):
            if down and t < 2 and i + 1 < h:
                _horizontal_row(cost, y + 1, p1, p2, lr, mins, min_keys,
                                hrows + (2 * t + (i + 1) % 2) * w, t == 1, total)
            if i < 0:
                continue
            slot = i % 3
            for x in range(bands[t], bands[t + 1]):
                if down:
                    forward = hrows + (i % 2) * w + x
                    backward = forward + 2 * w
                    for d in range(nd):
                        total[y, x, d] = _as(total, lr[forward, d + 1] + lr[backward, d + 1])
                for k in range(ndirs):
                    px = x - dirs[k, 0]
                    cur = (3 * k + slot) * w + x
                    if i >= dirs[k, 1] and 0 <= px < w:
                        back = slot - dirs[k, 1]  # (i - dy) % 3, dy <= 2
                        back += 3 if back < 0 else 0
                        _path_step(cost, y, x, lr, mins, min_keys, (3 * k + back) * w + px,
                                   cur, p1, p2, total, True)
                    else:
                        _path_start(cost, y, x, lr, min_keys, cur, total, True)


def _bands(w: int, ndirs: int, horizontal: bool, tasks: int) -> npt.NDArray[np.int64]:
    """
    Return the column bands (a boundary array) of `tasks` >= 2 tasks with equal work per row.

    A cell costs `ndirs` path steps; with `horizontal`, tasks 0 and 1 also walk a row of w.
    """
    extra = np.zeros(tasks)
    if horizontal:
        extra[:2] = w
    share = (w * ndirs + extra.sum()) / tasks
    width = np.maximum(share - extra, 0) / ndirs
    return np.round(np.concatenate([[0], np.cumsum(width)]) * w / width.sum()).astype(np.int64)


@njit(parallel=True, cache=True, nogil=True)
def _scan(cost: np.ndarray) -> tuple[int, Any]:
    """Return (number of cells that are negative, NaN or infinite, largest value)."""
    flat = cost.reshape(-1)
    n = 0
    top = np.zeros(1, flat.dtype)[0]
    for i in prange(flat.shape[0]):
        v = flat[i]
        if not (0 <= v < np.inf):
            n += 1
        top = max(top, v)
    return n, top


def as_volume(a: np.ndarray) -> np.ndarray:
    """
    Return `a` as a C-contiguous volume SGM takes.

    uint16 stays uint16, the rest becomes float32.
    """
    return np.ascontiguousarray(a, dtype=np.uint16 if a.dtype == np.uint16 else np.float32)


def penalties(dtype: np.dtype, p1: float, p2: float, paths: int, top: float
              ) -> tuple[Any, Any]:
    """
    Return P1 and P2 as `dtype` scalars for a volume whose largest cost is `top`.

    ValueError unless 0 <= P1 <= P2, `paths` is 4, 8 or 16 and, for uint16, P1 and P2 are
    integers and paths * (top + P2) is at most 65535.
    """
    p1, p2 = float(p1), float(p2)
    if not (0 <= p1 <= p2):
        raise ValueError(f'SGM penalties need 0 <= P1 <= P2, got P1={p1}, P2={p2}')
    directions(paths)
    dtype = np.dtype(dtype)
    if dtype == np.uint16:
        if not (p1.is_integer() and p2.is_integer()):
            raise ValueError(f'a uint16 cost volume needs integer penalties, got P1={p1}, P2={p2}')
        if path_sum_bound(paths, int(top), p2) > UINT16_MAX:
            raise ValueError(f'uint16 path sums would overflow: {paths} paths * '
                             f'(max cost {top} + P2 {p2:g}) > {UINT16_MAX}; '
                             'use a float32 volume')
    return dtype.type(p1), dtype.type(p2)


def aggregate(cost: npt.ArrayLike, p1: float, p2: float, paths: int = 16,
              out: np.ndarray | None = None, cancel: CancelFlag | None = None) -> np.ndarray:
    """
    Return the summed path costs S (H, W, D) of a cost volume (see module doc).

    S has the volume's type: uint16 for a uint16 volume, else float32.

    Costs must be finite and >= 0 (every matching cost here is); ValueError otherwise. For
    uint16, P1 and P2 must be integers and paths * (max cost + P2) at most 65535.
    `out`: an array to write S into (see `cost.output_array`), not `cost` itself.
    `cancel`: a CancelFlag; once set, the remaining rows are skipped (S is then incomplete).
    """
    cost = as_volume(np.asarray(cost))
    if cost.ndim != 3 or 0 in cost.shape:
        raise ValueError('cost volume must have shape (H, W, D) with no empty axis, '
                         f'got {cost.shape}')
    bad, top = _scan(cost)
    if bad:
        raise ValueError(f'cost volume has {bad} cells that are negative, NaN or infinite; '
                         'SGM needs finite costs >= 0')
    p1, p2 = penalties(cost.dtype, p1, p2, paths, top)
    total = output_array(out, cost.shape, cost.dtype)
    if np.shares_memory(total, cost):
        raise ValueError('out must not overlap the cost volume')
    flag = flag_array(cancel)
    down = np.array([d for d in directions(paths) if d[1] > 0], np.int64)
    # Seen from a bottom-up sweep, (dx, dy) from below is (-dx, dy) from above.
    up = np.array([(-dx, dy) for dx, dy in down], np.int64)
    tasks = max(2, numba.get_num_threads())
    w = cost.shape[1]
    sentinel = _sentinel(cost.dtype, p1)
    _sweep(cost, p1, p2, total, down, True, _bands(w, len(down), True, tasks), sentinel, flag)
    _sweep(cost, p1, p2, total, up, False, _bands(w, len(up), False, tasks), sentinel, flag)
    return total


@njit(inline='always')
def parabola_offset(lo: float, mid: float, hi: float) -> float:
    """
    Return the sub-pixel offset of a parabola's minimum through S at d - 1, d, d + 1.

    In float64, 0 unless the parabola opens upwards: the CPU and CUDA WTA share it, so their
    sub-pixel disparities round alike.
    """
    lo, mid, hi = float(lo), float(mid), float(hi)
    curv = lo - 2.0 * mid + hi
    return (lo - hi) / (2.0 * curv) if curv > 0 else 0.0


@njit(parallel=True, cache=True, nogil=True, fastmath=True)
def _wta(total: np.ndarray, subpixel: bool, lr_tol: int, shift: int, out: np.ndarray,
         consistent: np.ndarray, s_best: np.ndarray, s_second: np.ndarray, cancel: np.ndarray
         ) -> None:
    h, w, nd = total.shape
    low = np.int64((1 << shift) - 1)
    for y in prange(h):
        if cancel[0]:
            continue
        # Right view (lr_tol >= 0): the first argmin_d S(y, xr + d, d) of each right pixel xr,
        # as running minima over the left pixels x = xr + d (d grows with x) of the packed
        # key(S) << shift | d, whose least is the least S at its first d; kept at w - 1 - xr:
        # for one x the right pixels x - d, d = 0, 1, ..., are then a forward run of one min,
        # which vectorizes.
        right = np.empty(w if lr_tol >= 0 else 0, np.int64)
        for x in range(w if lr_tol >= 0 else 0):
            j = np.uint64(w - 1 - x)  # unsigned: no wraparound test, so the run vectorizes
            # d = 0: right pixel x's first
            right[j] = np.int64(_key(total[y, x, 0])) << shift  # type: ignore[call-arg]
            for d in range(1, min(nd, x + 1)):
                right[j + np.uint64(d)] = min(right[j + np.uint64(d)],
                                              (np.int64(_key(total[y, x, d])) << shift) | d)
        for x in range(w):
            # S >= 0: the first d whose key equals the minimum's
            m: Any = _key(total[y, x, 0])  # type: ignore[call-arg]
            for d in range(1, nd):
                m = min(m, _key(total[y, x, d]))
            best = 0
            while _key(total[y, x, best]) != m:
                best += 1
            # min S(d) over |d - best| > 1 (the best match not beside the winner): two runs
            rival = _top_key(total)
            for d in range(best - 1):
                rival = min(rival, _key(total[y, x, d]))
            for d in range(best + 2, nd):
                rival = min(rival, _key(total[y, x, d]))
            s_best[y, x] = total[y, x, best]
            s_second[y, x] = _key_value(rival) if best >= 2 or best + 2 < nd else np.inf
            offset = 0.0
            if subpixel and 0 < best < nd - 1:
                offset = parabola_offset(total[y, x, best - 1], total[y, x, best],
                                         total[y, x, best + 1])
            if lr_tol >= 0:  # the right view's winner at xr = x - best, if inside the image
                xr = x - best
                consistent[y, x] = xr >= 0 and abs((right[w - 1 - xr] & low) - best) <= lr_tol
            out[y, x] = best + offset


def winners(total: npt.ArrayLike, subpixel: bool = False, lr_check: bool = False,
            cancel: CancelFlag | None = None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """
    Return (disparity, consistent, s_best, s_second): the winner-takes-all of summed costs S.

    S is uint16, or finite and >= 0 as `aggregate` returns them (ValueError otherwise); the
    first minimum wins on ties. float32 (H, W) disparity (with `subpixel`, a parabola fit
    through the minimum and its neighbours); bool (H, W) `consistent`, False where the
    right-view winner at x - d differs from d by more than 1 px or x - d < 0 (all True
    without `lr_check`); float32 (H, W) `s_best` = S(d) of the winner and `s_second` = the least
    S(d) over |d - winner| > 1 (inf where no such d exists), which the uniqueness test and
    the confidence use. `cuda.sgm.winners` is the GPU twin. `cancel`: a CancelFlag; once
    set, the remaining rows are skipped.
    """
    total = as_volume(np.asarray(total))
    bad = _scan(total)[0] if total.dtype == np.float32 else 0
    if bad:
        raise ValueError(f'summed path costs have {bad} cells that are negative, NaN or infinite')
    out, s_best, s_second = (np.empty(total.shape[:2], np.float32) for _ in range(3))
    consistent = np.ones(total.shape[:2], np.bool_)
    _wta(total, subpixel, 1 if lr_check else -1, max(1, (total.shape[2] - 1).bit_length()),
         out, consistent, s_best, s_second, flag_array(cancel))
    return out, consistent, s_best, s_second


@njit(cache=True, nogil=True)
def costs_at(total: np.ndarray, rows: np.ndarray, cols: np.ndarray, disparities: np.ndarray
             ) -> np.ndarray:
    """Return total[rows[i], cols[i], disparities[i, j]], (n, k) of total's type."""
    n, k = disparities.shape
    out = np.empty((n, k), total.dtype)
    for i in range(n):
        for j in range(k):
            out[i, j] = total[rows[i], cols[i], disparities[i, j]]
    return out
