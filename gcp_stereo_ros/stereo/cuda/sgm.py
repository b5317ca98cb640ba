"""
CUDA twin of sgm.py: path costs, their sum S and the winner-takes-all in GPU memory.

The layout of libSGM (Hernandez-Juarez et al. 2016, "Embedded real-time stereo estimation via
Semi-Global Matching on the GPU"): a group of nl = `lanes(D)` threads of one warp (8, 16 or
32) walks one path, lane l holding L_r(p, d) of d = l, l + nl, ... in registers (k = D / nl
of them, rounded up; D, nl and k are constants of the kernel compiled for that D). Neighbouring
lanes read and write neighbouring d of the (H, W, D) volume: a warp's load of 32 uint16
costs touches two 32-byte sectors (four for float32). At each step a lane gets
L_r(p - r, d -+ 1) from its cyclic neighbours and min_d L_r(p - r, d) of the group through
`cuda.lanes.exchange` (warp shuffles, no barrier: each group steps on by itself), and reads
C of the pixel AHEAD steps on, so loads are in flight while the chain of steps runs. The
arithmetic is float32 for both volume types (uint16 sums stay below 2^17: exact), each L_r
computed as (C - min L_r(p - r)) + the best predecessor term: the order in which the CPU's
compiler evaluates `sgm._path_step` (fastmath), so float32 path costs round alike (the
simulator checks catch it if that order changes).

All directions run in one launch, the long horizontal paths first (a block holds
`gpu.THREADS // nl` paths of one direction). S must equal the CPU's float32 sums, which add
the L_r in `sgm.summation_order`: float addition is not associative, so concurrent
directions cannot add into S as they go (atomics would add in whatever order they arrive).
Each direction writes its own L_r volume instead (the first into S itself), and a second
kernel adds them in that order: paths - 1 extra volumes of the volume's type (1.8 GB for a
uint16 KITTI volume at D = 128 and 16 paths) and about 2 (paths - 1) volumes more memory
traffic than a sum in place. The penalties and limits are the CPU's (`sgm.penalties`).

The WTA, with the same lanes across the d of one pixel, its S in registers: the first
minimum and the least S outside best +- 1 by `cuda.lanes.lanes_argmin`, the sub-pixel fit of
`sgm.parabola_offset`; the left-right check reads the right view's winners, which a kernel of
their own finds first with lanes along a diagonal of the volume (see `_right_winners`), so
that also reads coalesced.
"""
from functools import cache
from typing import Any

from numba import cuda, float32, int32, njit, uint64
import numpy as np
import torch

from . import gpu
from .lanes import exchange, exchange_bytes, lanes, lanes_argmin, per_lane, THREADS, WARP
from ..sgm import parabola_offset, penalties, summation_order

INF = np.float32(np.inf)
AHEAD = 4  # steps whose costs a path's lanes read before the step that uses them


@njit(inline='always')  # kernels call it too (it compiles for a GPU without one)
def _starts(h: int, w: int, dx: int, dy: int) -> int:
    """Return the number of paths of direction (dx, dy): pixels whose predecessor is outside."""
    rows = min(abs(dy), h)
    return rows * w + min(abs(dx), w) * (h - rows)


@njit(inline='always')
def _start(b: int, h: int, w: int, dx: int, dy: int) -> tuple[int, int]:
    """Return (x, y) of the b-th pixel whose predecessor (x - dx, y - dy) is outside."""
    rows = min(abs(dy), h)
    if b < rows * w:  # in the |dy| rows the path enters through
        y = b // w
        return b % w, (y if dy > 0 else h - 1 - y)
    b -= rows * w
    c, y = b // (h - rows), b % (h - rows)  # in the |dx| columns, the other rows
    return (c if dx > 0 else w - 1 - c), (y + rows if dy > 0 else y)


@njit(inline='always')
def _length(x: int, y: int, h: int, w: int, dx: int, dy: int) -> int:
    """Return the number of pixels of the path from (x, y) in direction (dx, dy)."""
    n = h + w
    if dx != 0:
        n = min(n, ((w - 1 - x) if dx > 0 else x) // abs(dx) + 1)
    if dy != 0:
        n = min(n, ((h - 1 - y) if dy > 0 else y) // abs(dy) + 1)
    return n


@cache
def _path_kernel(nd: int) -> Any:
    """Return the path kernel for volumes of `nd` disparities (a constant of its code)."""
    nl, k = lanes(nd), per_lane(nd)
    queue = AHEAD * k  # a constant for the local array's size
    full = nd == k * nl  # every lane's every d inside D

    @cuda.jit
    def _paths(cost: gpu.DeviceArray, total: gpu.DeviceArray, lines: gpu.DeviceArray,
               dirs: gpu.DeviceArray, p1: float, p2: float) -> None:
        """
        Write L_r of every direction: the first into `total`, the j-th into lines[j - 1].

        `dirs` (n, 3): dx, dy and the first block of each direction, in summation order.
        Block (nl, group): `group` paths of one direction, nl lanes each.
        """
        h, w = cost.shape[:2]
        lane = cuda.threadIdx.x
        blk = cuda.blockIdx.x
        r = 0
        while r + 1 < dirs.shape[0] and dirs[r + 1, 2] <= blk:
            r += 1
        dx, dy = dirs[r, 0], dirs[r, 1]
        path = (blk - dirs[r, 2]) * cuda.blockDim.y + cuda.threadIdx.y
        if path >= _starts(h, w, dx, dy):
            return
        out = total if r == 0 else lines[r - 1]
        x, y = _start(path, h, w, dx, dy)
        steps = _length(x, y, h, w, dx, dy)
        here = cuda.local.array(k, float32)  # L_r(p, d) at d = lane + i nl, inf past D
        above = cuda.local.array(k, float32)  # here[i] of the lane before (d - 1), cyclic
        below = cuda.local.array(k, float32)  # here[i] of the lane after (d + 1), cyclic
        coming = cuda.local.array(queue, float32)  # C of the next AHEAD pixels
        fresh = cuda.local.array(k, float32)
        # Indices as uint64 (free casts of values >= 0): Numba then adds no negative-index
        # wrap-around, and the compiler turns the path's addresses into increments.
        dest = out[uint64(y), uint64(x)]
        low = INF
        for i in range(k):  # L_r = C where the path enters
            d = lane + i * nl
            here[i] = INF
            if full or d < nd:
                c = cost[uint64(y), uint64(x), uint64(d)]
                dest[uint64(d)] = c
                here[i] = float32(c)
                low = min(low, here[i])
                for a in range(AHEAD):
                    if a + 1 < steps:
                        coming[a * k + i] = cost[uint64(y + (a + 1) * dy),
                                                 uint64(x + (a + 1) * dx), uint64(d)]
        for t in range(1, steps):
            if t + AHEAD < steps:  # the pixel AHEAD steps on, read before it is needed
                ya, xa = uint64(y + (AHEAD + 1) * dy), uint64(x + (AHEAD + 1) * dx)
                for i in range(k):
                    d = lane + i * nl
                    if full or d < nd:
                        fresh[i] = cost[ya, xa, uint64(d)]
            m = exchange(here, low, lane, nl, t, above, below)  # min_d L_r(p - r, d)
            x += dx
            y += dy
            dest = out[uint64(y), uint64(x)]
            jump = m + p2
            low = INF
            for i in range(k):
                d = lane + i * nl
                left = above[i] if lane > 0 else (above[i - 1] if i > 0 else INF)
                right = below[i] if lane < nl - 1 else (below[i + 1] if i + 1 < k else INF)
                if full or d < nd:
                    best = min(min(here[i], jump), min(left, right) + p1)
                    v = (coming[i] - m) + best  # as the CPU's compiler orders it
                    dest[uint64(d)] = v
                    here[i] = v
                    low = min(low, v)
                for a in range(AHEAD - 1):
                    coming[a * k + i] = coming[(a + 1) * k + i]
                coming[(AHEAD - 1) * k + i] = fresh[i]

    return _paths


@cuda.jit
def _path_sum(total: gpu.DeviceArray, lines: gpu.DeviceArray) -> None:
    """Set total = ((L_0 + L_1) + L_2) + ... per cell (flat): `total` holds L_0, lines[k] L_k+1."""
    i = cuda.grid(1)
    if i >= total.shape[0]:
        return
    v = total[i]
    for k in range(lines.shape[0]):
        v = v + lines[k, i]
    total[i] = v


def aggregate(cost: torch.Tensor, p1: float, p2: float, paths: int, top: float,
              out: torch.Tensor | None = None) -> torch.Tensor:
    """
    Return the summed path costs S of a cost volume tensor on the GPU, as `sgm.aggregate`.

    `cost`: (H, W, D) uint16 or float32 with costs >= 0 (not checked: the pipeline's own
    kernels make it); `top`: its largest value, for the uint16 limit (its maker knows it).
    `out`: a tensor to write S into, or None. Returns S, a tensor of the volume's type, equal
    to the CPU's. Needs paths - 1 volumes of working memory besides.
    """
    h, w, nd = cost.shape
    p1, p2 = penalties(gpu.numpy_type(cost), p1, p2, paths, top)
    total = torch.empty_like(cost) if out is None else out
    order = summation_order(paths)
    nl = lanes(nd)
    group = THREADS // nl
    dirs, blocks = [], 0
    for dx, dy in order:
        dirs.append((dx, dy, blocks))
        blocks += -(-_starts(h, w, dx, dy) // group)
    dirs = torch.tensor(dirs, dtype=torch.int32).to(cost.device)
    lines = torch.empty((len(order) - 1,) + cost.shape, dtype=cost.dtype, device=cost.device)
    gpu.launch_blocks(_path_kernel(nd), blocks, (nl, group), exchange_bytes(per_lane(nd)),
                      cost, total, lines, dirs, np.float32(p1), np.float32(p2))
    gpu.launch(_path_sum, total.numel(), total.view(-1), lines.view(len(order) - 1, -1))
    return total


@cuda.jit
def _right_winners(total: gpu.DeviceArray, rbest: gpu.DeviceArray) -> None:
    """
    rbest[y, xr] = argmin_d S(y, xr + d, d) over xr + d < W (first minimum): the right WTA.

    One thread per right pixel; lane j of a warp takes d = t - j at step t, so at each step
    the warp reads consecutive d of one pixel (xr - j + t).
    """
    h, w, nd = total.shape
    i = cuda.grid(1)
    if i >= h * w:
        return
    y, xr = i // w, i % w
    j = cuda.threadIdx.x % WARP
    top = min(nd, w - xr)
    best = 0
    low = INF
    for t in range(WARP + nd - 1):  # the same count in every lane: they stay in step
        d = t - j
        if 0 <= d < top:
            v = float32(total[y, xr + d, d])
            if v < low:
                best, low = d, v
    rbest[y, xr] = best


@cache
def _winner_kernel(nd: int) -> Any:
    """Return the WTA kernel for volumes of `nd` disparities (a constant of its code)."""
    nl, k = lanes(nd), per_lane(nd)

    @cuda.jit
    def _winners(total: gpu.DeviceArray, rbest: gpu.DeviceArray, subpixel: bool, lr_tol: int,
                 out: gpu.DeviceArray, consistent: gpu.DeviceArray, s_best: gpu.DeviceArray,
                 s_second: gpu.DeviceArray) -> None:
        """
        Write the CPU's `sgm._wta` (first minimum on ties), S(best), min S over |d - best| > 1.

        Block (nl, group): `group` pixels, the lanes of one across its d. `rbest` is the
        right view's winners (from `_right_winners`) when lr_tol >= 0.
        """
        h, w = total.shape[:2]
        lane = cuda.threadIdx.x
        i = cuda.blockIdx.x * cuda.blockDim.y + cuda.threadIdx.y
        if i >= h * w:
            return
        y, x = i // w, i % w
        s = cuda.local.array(k, float32)  # S(d) at d = lane + q nl, inf past D
        low, at = INF, int32(nd)  # int32: one shuffle a value
        for q in range(k):
            d = lane + q * nl
            s[q] = INF
            if d < nd:
                s[q] = float32(total[y, x, d])
                if s[q] < low:
                    low, at = s[q], int32(d)
        low, best = lanes_argmin(low, at, lane, nl, 0)
        second = INF
        for q in range(k):
            if abs(lane + q * nl - best) > 1:
                second = min(second, s[q])
        second = lanes_argmin(second, int32(0), lane, nl, 1)[0]
        if lane != 0:
            return
        s_best[y, x] = low
        s_second[y, x] = second
        offset = 0.0
        if subpixel and 0 < best < nd - 1:
            offset = parabola_offset(total[y, x, best - 1], total[y, x, best],
                                     total[y, x, best + 1])
        out[y, x] = best + offset
        if lr_tol >= 0:  # the right view's winner at xr = x - best
            xr = x - best
            consistent[y, x] = xr >= 0 and abs(rbest[y, max(xr, 0)] - best) <= lr_tol

    return _winners


def winners(total: torch.Tensor, subpixel: bool = False, lr_check: bool = False
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """
    Return the WTA of S on the GPU: (disparity, consistent, s_best, s_second), tensors (H, W).

    As `sgm.winners`': disparity float32, consistent bool (all True without `lr_check`),
    s_best = S(best d) and s_second = min S(d) over |d - best| > 1 (+inf where there is
    none), float32.
    """
    h, w, nd = total.shape
    device = total.device
    out = torch.empty((h, w), dtype=torch.float32, device=device)
    consistent = torch.ones((h, w), dtype=torch.bool, device=device)
    s_best = torch.empty((h, w), dtype=torch.float32, device=device)
    s_second = torch.empty((h, w), dtype=torch.float32, device=device)
    rbest = torch.zeros((h, w) if lr_check else (1, 1), dtype=torch.int32, device=device)
    if lr_check:
        gpu.launch(_right_winners, h * w, total, rbest)
    nl = lanes(nd)
    group = THREADS // nl
    gpu.launch_blocks(_winner_kernel(nd), -(-h * w // group), (nl, group), exchange_bytes(1),
                      total, rbest, bool(subpixel), 1 if lr_check else -1, out, consistent,
                      s_best, s_second)
    return out, consistent, s_best, s_second
