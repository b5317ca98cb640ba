"""
CUDA twin of sgm.py: path costs, their sum S and the winner-takes-all in GPU memory.

libSGM's layout (Hernandez-Juarez et al. 2016): a group of `lanes(D)` threads walks one
path, lane l holding disparities d = l, l + lanes, ..., so a warp's loads of the (H, W, D)
volume are coalesced; at each step a lane reads its neighbours' L_r(p - r, d +- 1) and the
lanes' partial minima from shared memory, double-buffered by step parity (one barrier a
step). The arithmetic is float32 for both volume types (uint16 sums stay below 2^17:
exact), each L_r computed as (C - min L_r(p - r)) + the best predecessor term, the order
in which the CPU's compiler evaluates `sgm._path_step`, so float32 path costs round alike
(the simulator checks catch it if that order changes).

All directions run in one launch (a block holds `gpu.THREADS // lanes` paths of one
direction). S must equal the CPU's float32 sums, added in
`sgm.summation_order`, so each direction writes its own L_r volume (the first into S) and
a second kernel adds them in that order: paths - 1 volumes of working memory. The WTA puts
the same lanes across the d of one pixel; the left-right check reads the right view's
winners, found first by `_right_winners`. Penalties and limits are the CPU's
(`sgm.penalties`). Layout, sizes and counts: doc/speed.md, "SGM and WTA on the GPU".
"""
from numba import cuda, float32, int32, njit
import numpy as np
import torch

from . import gpu
from .sgm import parabola_offset, penalties, summation_order

LANES = 32  # most threads per path and per WTA pixel: a warp
THREADS = gpu.THREADS  # per block (a constant the kernels can size shared arrays with)
INF = np.float32(np.inf)
SHARED_BYTES = 48 * 1024  # the most dynamic shared memory a block gets without opting in


def lanes(nd):
    """Return the threads a path (or a WTA pixel) of D = `nd` disparities gets: 8, 16 or 32."""
    return min(LANES, max(8, 1 << (nd - 1).bit_length()))


@njit(inline='always')  # kernels call it too (it compiles for a GPU without one)
def _starts(h, w, dx, dy):
    """Return the number of paths of direction (dx, dy): pixels whose predecessor is outside."""
    rows = min(abs(dy), h)
    return rows * w + min(abs(dx), w) * (h - rows)


@njit(inline='always')
def _start(b, h, w, dx, dy):
    """Return (x, y) of the b-th pixel whose predecessor (x - dx, y - dy) is outside."""
    rows = min(abs(dy), h)
    if b < rows * w:  # in the |dy| rows the path enters through
        y = b // w
        return b % w, (y if dy > 0 else h - 1 - y)
    b -= rows * w
    c, y = b // (h - rows), b % (h - rows)  # in the |dx| columns, the other rows
    return (c if dx > 0 else w - 1 - c), (y + rows if dy > 0 else y)


@njit(inline='always')
def _length(x, y, h, w, dx, dy):
    """Return the number of pixels of the path from (x, y) in direction (dx, dy)."""
    n = h + w
    if dx != 0:
        n = min(n, ((w - 1 - x) if dx > 0 else x) // abs(dx) + 1)
    if dy != 0:
        n = min(n, ((h - 1 - y) if dy > 0 else y) // abs(dy) + 1)
    return n


@cuda.jit
def _paths(cost, total, lines, dirs, p1, p2):
    """
    Write L_r of every direction: the first into `total`, the k-th into lines[k - 1].

    `dirs` (n, 3): dx, dy and the first block of each direction. Block (lanes, group): its
    `group` paths of one direction; dynamic shared memory per path: L_r(p - r, .) and the
    lanes' minima of it, for two steps.
    """
    h, w, nd = cost.shape
    nl, group = cuda.blockDim.x, cuda.blockDim.y
    lane, j = cuda.threadIdx.x, cuda.threadIdx.y
    blk = cuda.blockIdx.x
    k = 0
    while k + 1 < dirs.shape[0] and dirs[k + 1, 2] <= blk:
        k += 1
    dx, dy = dirs[k, 0], dirs[k, 1]
    out = total if k == 0 else lines[k - 1]
    n = _starts(h, w, dx, dy)
    first = (blk - dirs[k, 2]) * group
    longest = 0  # the block's longest path: all its threads pass as many barriers
    steps = 0
    x = y = 0
    for i in range(group):
        if first + i < n:
            px, py = _start(first + i, h, w, dx, dy)
            size = _length(px, py, h, w, dx, dy)
            longest = max(longest, size)
            if i == j:
                x, y, steps = px, py, size
    shared = cuda.shared.array(0, float32)
    line = j * 2 * (nd + nl)  # L_r of step parity s at line + s * nd + d
    mins = line + 2 * nd  # the lanes' minima at mins + s * nl + lane
    if steps > 0:  # L_r = C where the path enters
        low = INF
        for d in range(lane, nd, nl):
            c = cost[y, x, d]
            out[y, x, d] = c
            v = float32(c)
            shared[line + d] = v
            low = min(low, v)
        shared[mins + lane] = low
    cuda.syncthreads()
    s = 0
    for t in range(1, longest):
        if t < steps:
            x += dx
            y += dy
            m = shared[mins + s * nl]  # min_d L_r(p - r, d)
            for i in range(1, nl):
                m = min(m, shared[mins + s * nl + i])
            jump = m + p2
            low = INF
            for d in range(lane, nd, nl):
                prev = line + s * nd + d
                best = min(shared[prev], jump)
                if d > 0:
                    best = min(best, shared[prev - 1] + p1)
                if d + 1 < nd:
                    best = min(best, shared[prev + 1] + p1)
                v = (float32(cost[y, x, d]) - m) + best  # as the CPU's compiler orders it
                out[y, x, d] = v
                shared[line + (1 - s) * nd + d] = v
                low = min(low, v)
            shared[mins + (1 - s) * nl + lane] = low
        cuda.syncthreads()
        s = 1 - s


@cuda.jit
def _path_sum(total, lines):
    """Set total = ((L_0 + L_1) + L_2) + ... per cell (flat): `total` holds L_0, lines[k] L_k+1."""
    i = cuda.grid(1)
    if i >= total.shape[0]:
        return
    v = total[i]
    for k in range(lines.shape[0]):
        v = v + lines[k, i]
    total[i] = v


def aggregate(cost, p1, p2, paths, top, out=None):
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
    per_path = 4 * 2 * (nd + nl)  # bytes of shared memory
    group = max(1, min(THREADS // nl, SHARED_BYTES // per_path))
    dirs, blocks = [], 0
    for dx, dy in order:
        dirs.append((dx, dy, blocks))
        blocks += -(-_starts(h, w, dx, dy) // group)
    dirs = torch.tensor(dirs, dtype=torch.int32).to(cost.device)
    lines = torch.empty((len(order) - 1,) + cost.shape, dtype=cost.dtype, device=cost.device)
    gpu.launch_blocks(_paths, blocks, (nl, group), group * per_path, cost, total, lines, dirs,
                      np.float32(p1), np.float32(p2))
    gpu.launch(_path_sum, total.numel(), total.view(-1), lines.view(len(order) - 1, -1))
    return total


@cuda.jit
def _right_winners(total, rbest):
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
    j = cuda.threadIdx.x % LANES
    top = min(nd, w - xr)
    best = 0
    low = INF
    for t in range(LANES + nd - 1):  # the same count in every lane: they stay in step
        d = t - j
        if 0 <= d < top:
            v = float32(total[y, xr + d, d])
            if v < low:
                best, low = d, v
    rbest[y, xr] = best


@cuda.jit
def _winners(total, rbest, subpixel, lr_tol, out, consistent, s_best, s_second):
    """
    Write the CPU's `sgm._wta` (first minimum on ties), S(best) and min S over |d - best| > 1.

    Block (lanes, group): `group` pixels, the lanes of one across its d. `rbest` is the right
    view's winners (from `_right_winners`) when lr_tol >= 0.
    """
    h, w, nd = total.shape
    nl, group = cuda.blockDim.x, cuda.blockDim.y
    lane, j = cuda.threadIdx.x, cuda.threadIdx.y
    i = cuda.blockIdx.x * group + j
    inside = i < h * w
    y, x = i // w, i % w
    low, at = INF, nd
    if inside:
        for d in range(lane, nd, nl):
            v = float32(total[y, x, d])
            if v < low:
                low, at = v, d
    values = cuda.shared.array(THREADS, float32)
    indices = cuda.shared.array(THREADS, int32)
    seconds = cuda.shared.array(THREADS, float32)
    values[j * nl + lane] = low
    indices[j * nl + lane] = at
    cuda.syncthreads()
    low, best = values[j * nl], indices[j * nl]
    for k in range(j * nl + 1, j * nl + nl):
        if values[k] < low or (values[k] == low and indices[k] < best):
            low, best = values[k], indices[k]
    second = INF
    if inside:
        for d in range(lane, nd, nl):
            v = float32(total[y, x, d])  # read by every lane: one load of the warp
            if abs(d - best) > 1:
                second = min(second, v)
    seconds[j * nl + lane] = second
    cuda.syncthreads()
    if not inside or lane != 0:
        return
    for k in range(j * nl + 1, j * nl + nl):
        second = min(second, seconds[k])
    s_best[y, x] = low
    s_second[y, x] = second
    offset = 0.0
    if subpixel and 0 < best < nd - 1:
        offset = parabola_offset(total[y, x, best - 1], total[y, x, best], total[y, x, best + 1])
    out[y, x] = best + offset
    if lr_tol >= 0:  # the right view's winner at xr = x - best
        xr = x - best
        consistent[y, x] = xr >= 0 and abs(rbest[y, max(xr, 0)] - best) <= lr_tol


def winners(total, subpixel=False, lr_check=False):
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
    gpu.launch_blocks(_winners, -(-h * w // group), (nl, group), 0, total, rbest,
                      bool(subpixel), 1 if lr_check else -1, out, consistent, s_best, s_second)
    return out, consistent, s_best, s_second
