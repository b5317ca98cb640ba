"""
The CNN confidence on a GPU: the torch twin of `cnn`'s correlation kernels.

The descriptors of each strip (`cnn.descriptors`, L2-normalized in float32) are correlated
in torch on the device, as batched matrix products over blocks of BAND_BLOCK columns
(`_band_volume`); without a filter the best disparities are taken from each strip's volume
(`_band_best`; the right view as the left view of the mirrored pair), with one the strip's
volume, with its halo of rows, is guided-filtered first (`filtered_best`, the twin of
`cnn.filter.filtered_best`). The results equal `cnn.confidence`'s within float rounding:
float32 work runs in IEEE float32 (`ieee_float32`), never TF32.
"""
from collections.abc import Iterator
from contextlib import contextmanager
import time

import torch
import torch.nn.functional as F

from ..cnn import filter as cnn_filter
from ..cnn.network import (calibrated, descriptors, EPS, GcpNet, PAD, resolve_precision,
                           STRIP_ROWS)
from ..cost import check_max_disp

BAND_BLOCK = 128  # columns per block of `_band_volume`


def _band_volume(fa: torch.Tensor, fb: torch.Tensor, max_disp: int) -> torch.Tensor:
    """
    Return Vol(r, x, d) = <fa[r, x], fb[r, x - d]>, d < max_disp, as (R, W, max_disp).

    `fa`, `fb`: unit descriptors (R, W, C) on one device; cells with x - d < 0 are 0 and
    dot products are capped at 1, as in `cnn._best_match`. Each block of BAND_BLOCK columns
    of `fa` is multiplied with the BAND_BLOCK + max_disp - 1 columns of `fb` it can see, all
    blocks in one batched matrix product: (1 + BAND_BLOCK / max_disp) times the band's work.
    """
    r, w, c = fa.shape
    nb = -(-w // BAND_BLOCK)
    a = F.pad(fa, (0, 0, 0, nb * BAND_BLOCK - w)).view(r, nb, BAND_BLOCK, c)
    seen = BAND_BLOCK + max_disp - 1
    b = F.pad(fb, (0, 0, max_disp - 1, nb * BAND_BLOCK - w)).unfold(1, seen, BAND_BLOCK)
    m = a @ b  # (r, nb, BAND_BLOCK, seen): column j holds fb at x - d for j = i + D - 1 - d
    i = torch.arange(BAND_BLOCK, device=fa.device)
    j = i[:, None] + (max_disp - 1) - torch.arange(max_disp, device=fa.device)
    vol = m.gather(3, j.expand(r, nb, -1, -1)).view(r, nb * BAND_BLOCK, max_disp)[:, :w]
    return vol.clamp_(max=1.0)


def _band_best(fa: torch.Tensor, fb: torch.Tensor, max_disp: int
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Return max_d and first argmax_d of `_band_volume`, (R, W) each."""
    vol = _band_volume(fa, fb, max_disp)
    return vol.amax(2), vol.argmax(2)  # argmax: the first maximum


@contextmanager
def ieee_float32() -> Iterator[None]:
    """
    Run float32 convolutions and matrix products in IEEE float32 for the duration.

    cuDNN takes TF32 (a 10-bit mantissa) for float32 convolutions by default on GPUs of
    compute capability 8.0 or more, and torch's matrix products do where a program asked
    for it (`torch.set_float32_matmul_precision`), which moves the confidence of
    `precision: fp32` away from the CPU's (doc/notes/speed_report.md). bfloat16 work is not
    affected.
    """
    backends = (torch.backends.cudnn.conv, torch.backends.cuda.matmul)
    before = [b.fp32_precision for b in backends]
    for b in backends:
        b.fp32_precision = 'ieee'
    try:
        yield
    finally:
        for b, precision in zip(backends, before):
            b.fp32_precision = precision


def device_confidence(net: GcpNet, x: torch.Tensor, max_disp: int, precision: str = 'fp32',
                      seconds: dict[str, float] | None = None, radius: int = 0
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """
    Return `cnn.confidence`'s (cof_c, cof_d, cof_dr) as tensors on the device of `x`.

    `x`: the pair as `cnn.padded_input` makes it, on the net's device; `precision`: 'auto',
    'bf16' or 'fp32' (`cnn.resolve_precision`); `radius`: of the guided filter (0: none).
    `seconds`: a dict that gains the device time of the
    convolutions ('cnn') and of the correlation ('confidence'), waiting for the device at
    each strip's stages; None: not timed, nothing waits.
    """
    h, w = x.shape[2] - 2 * PAD, x.shape[3] - 2 * PAD
    check_max_disp(max_disp, w)
    precision = resolve_precision(precision, x.device)
    cof_c = torch.empty((h, w), dtype=torch.float32, device=x.device)
    cof_d = torch.empty((h, w), dtype=torch.int32, device=x.device)
    cof_dr = torch.empty((h, w), dtype=torch.int32, device=x.device)
    guide = x[0, 0, PAD:PAD + h, PAD:PAD + w]
    timed = seconds is not None
    for stage in ('cnn', 'confidence') if timed else ():
        seconds.setdefault(stage, 0.0)  # type: ignore[union-attr]  # timed: not None
    with torch.inference_mode(), ieee_float32():
        for y0 in range(0, h, STRIP_ROWS):
            y1 = min(y0 + STRIP_ROWS, h)
            lo, hi = max(0, y0 - cnn_filter.halo(radius)), min(h, y1 + cnn_filter.halo(radius))
            t = time.perf_counter()
            f = F.normalize(descriptors(net, x[:, :, lo:hi + 2 * PAD], precision).float(), dim=3,
                            eps=EPS)
            if timed:
                _synchronize(x.device)
            t1 = time.perf_counter()
            if radius:
                cof_c[y0:y1], cof_d[y0:y1], cof_dr[y0:y1] = filtered_best(
                    _band_volume(f[0], f[1], int(max_disp)), guide[lo:hi], radius, y0 - lo,
                    y1 - y0)
            else:
                cof_c[y0:y1], cof_d[y0:y1] = _band_best(f[0], f[1], int(max_disp))
                cof_dr[y0:y1] = _band_best(f[1].flip(1), f[0].flip(1), int(max_disp))[1].flip(1)
            if timed:
                _synchronize(x.device)
                seconds['cnn'] += t1 - t  # type: ignore[index]
                seconds['confidence'] += time.perf_counter() - t1  # type: ignore[index]
    return calibrated(net, cof_c, radius), cof_d, cof_dr


def _synchronize(device: torch.device) -> None:
    if device.type == 'cuda':
        torch.cuda.synchronize(device)


def _means(x: torch.Tensor, radius: int) -> torch.Tensor:
    """
    Return the window means of x (..., rows, W), each window clipped to x (`cnn.filter`).

    A clipped window is a rectangle, so its mean is the column mean of the row means: two
    passes of 2 r + 1 reads per pixel instead of one of (2 r + 1)^2.
    """
    k = 2 * radius + 1
    x = F.avg_pool2d(x, (k, 1), stride=1, padding=(radius, 0), count_include_pad=False)
    return F.avg_pool2d(x, (1, k), stride=1, padding=(0, radius), count_include_pad=False)


def filtered_best(vol: torch.Tensor, guide: torch.Tensor, radius: int, first: int, rows: int
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """
    Return (cof_c, cof_d, cof_dr) of a strip, the torch twin of `cnn.filter.filtered_best`.

    `vol`: the raw volume (rows with the halo, W, D) on the device, `guide` the standardized
    left image's same rows (rows with the halo, W); the strip is rows first .. first + rows.
    """
    p = vol.permute(2, 0, 1).contiguous()  # (D, rows, W): one image per disparity
    mean_i, mean_ii = _means(torch.stack([guide, guide * guide]), radius)
    var_i = (mean_ii - mean_i * mean_i).clamp_(min=0)
    mean_p, mean_ip = _means(p, radius), _means(p * guide, radius)
    a = (mean_ip - mean_i * mean_p) / (var_i + cnn_filter.GUIDE_EPS)
    b = mean_p - a * mean_i
    strip = slice(first, first + rows)
    filtered = _means(a, radius)[:, strip] * guide[strip] + _means(b, radius)[:, strip]
    nd, w = filtered.shape[0], filtered.shape[2]
    xs, ds = torch.arange(w, device=vol.device), torch.arange(nd, device=vol.device)
    filtered.masked_fill_((ds[:, None] > xs[None])[:, None], -torch.inf)  # x - d < 0
    # The right view, unfiltered: Vol(y, xr + d, d), -inf where xr + d leaves the image.
    cols = xs[None] + ds[:, None]  # (D, W)
    right = p[:, strip].gather(2, cols.clamp(max=w - 1)[:, None].expand(-1, rows, -1))
    right.masked_fill_((cols >= w)[:, None], -torch.inf)
    return filtered.amax(0), filtered.argmax(0).int(), right.argmax(0).int()
