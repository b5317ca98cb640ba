"""
CUDA twin of sgm.py: path costs, their sum S and the winner-takes-all in GPU memory.

One kernel launch per path direction r, one thread per path: the thread starts at a pixel
whose predecessor p - r lies outside the image and walks p, p + r, p + 2r, ... to the
border, computing L_r(p, .) over all d from the previous pixel's, which it keeps in its
column of a small buffer, and adding it into S. The paths of one direction never share a
pixel, so no two threads write one cell, and the directions run one after the other in
`sgm.summation_order`, the CPU's order: S equals the CPU's exactly for uint16 volumes, and
for float32 within float rounding (the CPU's compiler reassociates some of its sums).
The penalties and limits are the CPU's (`sgm.penalties`).
"""
import math

from numba import cuda, njit
import torch

from . import gpu
from .sgm import parabola_offset, penalties, summation_order


def _starts(h, w, dx, dy):
    """Return the number of paths of direction (dx, dy): pixels whose predecessor is outside."""
    rows = min(abs(dy), h)
    return rows * w + min(abs(dx), w) * (h - rows)


@njit(inline='always')  # kernels call it too (it compiles for a GPU without one)
def _start(b, h, w, dx, dy):
    """Return (x, y) of the b-th pixel whose predecessor (x - dx, y - dy) is outside."""
    rows = min(abs(dy), h)
    if b < rows * w:  # in the |dy| rows the path enters through
        y = b // w
        return b % w, (y if dy > 0 else h - 1 - y)
    b -= rows * w
    c, y = b // (h - rows), b % (h - rows)  # in the |dx| columns, the other rows
    return (c if dx > 0 else w - 1 - c), (y + rows if dy > 0 else y)


@cuda.jit
def _path(cost, total, line, n, p1, p2, dx, dy, first):
    """Write (`first`) or add L_(dx, dy) into `total`; `line` (D, n): each path's last L_r."""
    h, w, nd = cost.shape
    b = cuda.grid(1)
    if b >= n:
        return
    x, y = _start(b, h, w, dx, dy)
    m = cost[y, x, 0]  # min_d L_r(p, d)
    for d in range(nd):  # L_r = C where the path enters
        line[d, b] = cost[y, x, d]
        v = line[d, b]
        m = min(m, v)
        total[y, x, d] = v if first else total[y, x, d] + v
    x += dx
    y += dy
    while 0 <= x < w and 0 <= y < h:
        jump = m + p2
        below = line[0, b]  # L_r(p - r, d - 1), read before it is overwritten
        low = cost[y, x, 0] + jump  # >= L_r(p, 0): the min over d starts there
        for d in range(nd):
            here = line[d, b]
            best = min(here, jump)
            if d > 0:
                best = min(best, below + p1)
            if d + 1 < nd:
                best = min(best, line[d + 1, b] + p1)
            line[d, b] = cost[y, x, d] + best - m
            v = line[d, b]
            low = min(low, v)
            total[y, x, d] = v if first else total[y, x, d] + v
            below = here
        m = low
        x += dx
        y += dy


def aggregate(cost, p1, p2, paths, top, out=None):
    """
    Return the summed path costs S of a cost volume tensor on the GPU, as `sgm.aggregate`.

    `cost`: (H, W, D) uint16 or float32 with costs >= 0 (not checked: the pipeline's own
    kernels make it); `top`: its largest value, for the uint16 limit (its maker knows it).
    `out`: a tensor to write S into, or None. Returns S, a tensor of the volume's type.
    """
    h, w, nd = cost.shape
    p1, p2 = penalties(gpu.numpy_type(cost), p1, p2, paths, top)
    total = torch.empty_like(cost) if out is None else out
    order = summation_order(paths)
    n = max(_starts(h, w, dx, dy) for dx, dy in order)
    # Path costs in the arithmetic type of the volume: int32 holds every uint16 sum exactly.
    line = torch.empty((nd, n), dtype=torch.float32 if cost.dtype == torch.float32
                       else torch.int32, device=cost.device)
    if cost.dtype != torch.float32:
        p1, p2 = int(p1), int(p2)
    for k, (dx, dy) in enumerate(order):
        gpu.launch(_path, n, cost, total, line, _starts(h, w, dx, dy), p1, p2, dx, dy, k == 0)
    return total


@cuda.jit
def _wta(total, subpixel, lr_tol, out, consistent, s_best, s_second):
    """One thread per pixel: the CPU's `sgm._wta`, first minimum on ties."""
    h, w, nd = total.shape
    i = cuda.grid(1)
    if i >= h * w:
        return
    y, x = i // w, i % w
    best = 0
    for d in range(1, nd):
        if total[y, x, d] < total[y, x, best]:
            best = d
    rival = math.inf
    for d in range(nd):
        if abs(d - best) > 1 and total[y, x, d] < rival:
            rival = total[y, x, d]
    s_best[y, x] = total[y, x, best]
    s_second[y, x] = rival
    offset = 0.0
    if subpixel and 0 < best < nd - 1:
        offset = parabola_offset(total[y, x, best - 1], total[y, x, best], total[y, x, best + 1])
    out[y, x] = best + offset
    if lr_tol >= 0:  # the right view's winner at xr = x - best
        xr = x - best
        rbest = 0
        for d in range(1, min(nd, w - xr)):
            if total[y, xr + d, d] < total[y, xr + rbest, rbest]:
                rbest = d
        consistent[y, x] = abs(rbest - best) <= lr_tol


def winners(total, subpixel=False, lr_check=False):
    """
    Return `sgm.winners`' (disparity, consistent, s_best, s_second) of S on the GPU, as tensors.

    float32, bool, float32, float32 (H, W); consistent is all True without `lr_check`.
    """
    out, s_best, s_second = (torch.empty(total.shape[:2], dtype=torch.float32,
                                         device=total.device) for _ in range(3))
    consistent = torch.ones(total.shape[:2], dtype=torch.bool, device=total.device)
    gpu.launch(_wta, out.numel(), total, bool(subpixel), 1 if lr_check else -1, out, consistent,
               s_best, s_second)
    return out, consistent, s_best, s_second
