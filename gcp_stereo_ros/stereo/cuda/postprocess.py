"""
The invalidation on a GPU: the CUDA twin of `postprocess.invalidate` on device tensors.

The same tests in the same order mark the same pixels NaN as the host's, bit for bit: the
comparisons are torch's in the host's types (float32 thresholds as numpy rounds them), the
background test and the speckles numba-cuda kernels (`gpu.launch`):
- `fill_rows` of the pixels that stay, one thread per row (`_fill_rows`), then one thread
  per low-confidence pixel reads its summed costs in the volume itself (`_background_fits`);
- speckles are the connected components of cv2.filterSpeckles' graph (4-neighbours, both
  valid, whose fixed-point disparities differ by at most speckle_range * 16): a union-find
  (`_links`: each pair of neighbours joined by atomicMin on the larger root, so that a
  component's root is its least pixel index whatever the threads' order), then each
  pixel's root and the components' sizes (`_sizes`, atomic adds of integers): the result is
  deterministic.
"""
import math

from numba import cuda
import numpy as np
import torch

from . import gpu
from ..config import StereoConfig
from ..postprocess import depth_limits, inside, SPECKLE_SCALE

INVALID = -SPECKLE_SCALE  # filterSpeckles' newVal: -1 px in its fixed point
NAN = float('nan')


def _threshold(value: float) -> float:
    """Return `value` rounded to float32, as numpy compares a float32 array with it."""
    return float(np.float32(value))


def cut_short(disp: torch.Tensor, cfg: StereoConfig) -> torch.Tensor:
    """Return `postprocess.cut_short` of a device disparity, bool (h, w)."""
    x0, y0, x1, y1 = inside(cfg.window // 2, disp.shape)
    out = torch.ones(disp.shape, dtype=torch.bool, device=disp.device)
    out[y0:y1, x0:x1] = False
    x = torch.arange(disp.shape[1], dtype=torch.float64, device=disp.device)
    out |= (x < cfg.matched_disp - 1) & (x - disp.double() <= 1)  # numpy's float64
    return out


@cuda.jit
def _fill_rows(d: gpu.DeviceArray) -> None:
    """One thread per row y: `postprocess.fill_rows` of d[y], in place."""
    h, w = d.shape
    y = cuda.grid(1)
    if y >= h:
        return
    last = -1  # the column of the last finite pixel
    for x in range(w):
        v = d[y, x]
        if not math.isfinite(v):
            continue
        if last < x - 1:
            fill = v if last < 0 else min(d[y, last], v)
            for k in range(last + 1, x):
                d[y, k] = fill
        last = x
    if 0 <= last < w - 1:
        for k in range(last + 1, w):
            d[y, k] = d[y, last]


def backgrounds(disp: torch.Tensor, low: torch.Tensor) -> torch.Tensor:
    """Return `postprocess.backgrounds` of device tensors, float32 (h, w)."""
    out = torch.where(low, NAN, disp).contiguous()
    gpu.launch(_fill_rows, out.shape[0], out)
    return out.masked_fill_(~low, NAN)


@cuda.jit
def _background_fits(low: gpu.DeviceArray, at: gpu.DeviceArray, won: gpu.DeviceArray,
                     total: gpu.DeviceArray, top: int, ratio: float, fits: gpu.DeviceArray
                     ) -> None:
    """
    One thread per pixel: fits = low, but where a background's costs rule it out.

    `at`: the rounded background (NaN where none), `won`: the rounded disparity, float32
    (h, w); `total` the summed costs (h, w, D); disparities clipped to [0, top]; the least
    cost at the background and 1 px either side against `ratio` times the winner's, in
    float64 as the host.
    """
    h, w = low.shape
    i = cuda.grid(1)
    if i >= h * w:
        return
    y, x = i // w, i % w
    fit = low[y, x]
    b = at[y, x]
    if fit and math.isfinite(b):
        c = int(b)
        s0 = float(total[y, x, min(max(c - 1, 0), top)])
        s1 = float(total[y, x, min(max(c, 0), top)])
        s2 = float(total[y, x, min(max(c + 1, 0), top)])
        s3 = float(total[y, x, min(max(int(won[y, x]), 0), top)])
        fit = not min(min(s0, s1), s2) > ratio * s3
    fits[y, x] = fit


def background_fits(disp: torch.Tensor, low: torch.Tensor, total: torch.Tensor,
                    cfg: StereoConfig) -> torch.Tensor:
    """Return `postprocess.background_fits` of device tensors, reading `total` (h, w, D)."""
    fits = torch.empty_like(low)
    at = torch.round(backgrounds(disp, low))  # half to even, as np.rint
    gpu.launch(_background_fits, low.numel(), low, at, torch.round(disp), total,
               cfg.matched_disp - 1, np.float64(cfg.background_ratio), fits)
    return fits


@cuda.jit
def _links(fixed: gpu.DeviceArray, max_diff: int, label: gpu.DeviceArray) -> None:
    """
    One thread per pixel: join its tree to those of its right and lower neighbours.

    Where the two are of one speckle: the larger root goes under the smaller by atomicMin;
    `label` (h * w) points each pixel to a smaller index, to itself at a root, -1 where
    invalid.
    """
    h, w = fixed.shape
    i = cuda.grid(1)
    if i >= h * w:
        return
    y, x = i // w, i % w
    v = fixed[y, x]
    for k in range(2):  # the right and the lower neighbour
        ny, nx = y + k, x + 1 - k
        if v == INVALID or ny >= h or nx >= w:
            continue
        u = fixed[ny, nx]
        if u == INVALID or abs(u - v) > max_diff:
            continue
        a, b = i, ny * w + nx
        while True:
            while label[a] != a:  # the roots
                a = label[a]
            while label[b] != b:
                b = label[b]
            if a == b:
                break
            if a > b:
                a, b = b, a
            old = cuda.atomic.min(label, b, a)
            if old == b:  # b was a root still
                break
            b = old  # b was joined meanwhile: join what it was joined to


@cuda.jit
def _sizes(label: gpu.DeviceArray, size: gpu.DeviceArray) -> None:
    """One thread per valid pixel: point it to its root and count it into size[root]."""
    i = cuda.grid(1)
    if i >= label.shape[0] or label[i] < 0:
        return
    r = i
    while label[r] != r:
        r = label[r]
    label[i] = r
    cuda.atomic.add(size, r, 1)


def speckles(disp: torch.Tensor, size: float, max_diff: float) -> torch.Tensor:
    """Return `postprocess.speckles` of a device disparity: bool (h, w), cv2.filterSpeckles'."""
    finite = torch.isfinite(disp)
    fixed = torch.where(finite, torch.round(disp * SPECKLE_SCALE), INVALID)
    fixed = fixed.clamp(INVALID, np.iinfo(np.int16).max).to(torch.int32)
    n = disp.numel()
    index = torch.arange(n, dtype=torch.int32, device=disp.device)
    label = torch.where(fixed.view(-1) != INVALID, index, -1)
    counts = torch.zeros(n, dtype=torch.int32, device=disp.device)
    gpu.launch(_links, n, fixed, int(max_diff * SPECKLE_SCALE), label)
    gpu.launch(_sizes, n, label, counts)
    small = (label >= 0) & (counts[label.clamp(min=0).long()] <= int(size))
    return ((fixed.view(-1) == INVALID) | small).view(disp.shape) & finite


def invalidate(disp: torch.Tensor, consistent: torch.Tensor, m: torch.Tensor, cfg: StereoConfig,
               camera: tuple[float, float] | None = None,
               disparity_confidence: torch.Tensor | None = None,
               total: torch.Tensor | None = None, plain: torch.Tensor | None = None
               ) -> torch.Tensor:
    """
    Set NaN in `disp` (float32 tensor, in place) as `postprocess.invalidate`; return `disp`.

    Tensors on one device, (h, w) on the matching grid: `consistent` bool, `m` the float32
    margin, `disparity_confidence` float32 or None, `total` the summed SGM costs (h, w, D)
    (float32 or uint16) for the background test or None, `plain` plain SGM's float32
    disparity or None. The same pixels go as on the host, with the same arguments.
    """
    f = cfg.downsample
    if cfg.valid_window:
        disp.masked_fill_(cut_short(disp, cfg), NAN)
    if cfg.lr_check:
        disp.masked_fill_(~consistent, NAN)
    if cfg.uniqueness_ratio:
        disp.masked_fill_(m < _threshold(cfg.uniqueness_ratio / 100), NAN)
    limits = depth_limits(cfg, camera)
    if limits is not None:
        low, high = (_threshold(limit / f) for limit in limits)
        disp.masked_fill_((disp < low) | (disp > high), NAN)
    if cfg.min_confidence and disparity_confidence is not None:
        unsure = disparity_confidence < _threshold(cfg.min_confidence)
        if cfg.background_ratio and total is not None:
            unsure = background_fits(disp, unsure & torch.isfinite(disp), total, cfg)
        disp.masked_fill_(unsure, NAN)
    size = cfg.speckle_size // f ** 2
    if size:
        disp.masked_fill_(speckles(disp, size, cfg.speckle_range / f), NAN)
    if cfg.plain_check and plain is not None:
        disp.masked_fill_(disp - plain > _threshold(cfg.plain_check / f), NAN)
    return disp
