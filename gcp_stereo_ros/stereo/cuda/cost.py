"""
CUDA twins of cost.py's volumes: the same Census and SAD cells, on tensors in GPU memory.

One thread per pixel, looping over d as the CPU kernels do. Census costs are integers and
equal the CPU's exactly; SAD sums each window directly, in another order than the CPU's
sliding sums, so it agrees within float32 rounding.
"""
from typing import Any

from numba import cuda, njit
import numpy as np
import torch

from . import gpu
from ..cost import check_max_disp, max_cost, volume_type
from ..costs import cost_spec


@cuda.jit
def _census_transform(gray: Any, rad: int, bits: Any) -> None:
    """Write the Census bit strings of `gray` (H, W) into `bits` (2, H, W), as cost.py does."""
    h, w = gray.shape
    i = cuda.grid(1)
    if i >= h * w:
        return
    y, x = i // w, i % w
    centre = gray[y, x]
    lo = np.uint64(0)
    hi = np.uint64(0)
    k = 0
    for dy in range(-rad, rad + 1):
        yy = min(max(y + dy, 0), h - 1)  # the edge pixel repeated, as np.pad(mode='edge')
        for dx in range(-rad, rad + 1):
            if dy == 0 and dx == 0:
                continue
            xx = min(max(x + dx, 0), w - 1)
            if gray[yy, xx] < centre:
                if k < 64:
                    lo |= np.uint64(1) << np.uint64(k)
                else:
                    hi |= np.uint64(1) << np.uint64(k - 64)
            k += 1
    bits[0, y, x] = lo
    bits[1, y, x] = hi


@cuda.jit
def _census_cost(left: Any, right: Any, rad: int, scale: int, invalid: Any, out: Any) -> None:
    """Write scale * Hamming(left bits at x, right bits at x - d) into each valid cell."""
    h, w, nd = out.shape
    y, x, valid = _pixel(cuda.grid(1), h, w, nd, rad)
    if y < 0:
        return
    for d in range(valid):
        out[y, x, d] = (cuda.popc(left[0, y, x] ^ right[0, y, x - d])
                        + cuda.popc(left[1, y, x] ^ right[1, y, x - d])) * scale
    for d in range(valid, nd):
        out[y, x, d] = invalid


@cuda.jit
def _sad_cost(left: Any, right: Any, rad: int, scale: Any, invalid: Any, out: Any) -> None:
    """Write min(scale * mean |left - right shifted by d| over the window, invalid)."""
    h, w, nd = out.shape
    y, x, valid = _pixel(cuda.grid(1), h, w, nd, rad)
    if y < 0:
        return
    area = np.float32((2 * rad + 1) ** 2)
    for d in range(valid):
        s = np.float32(0.0)
        for yy in range(y - rad, y + rad + 1):
            for xx in range(x - rad, x + rad + 1):
                s += abs(left[yy, xx] - right[yy, xx - d])
        out[y, x, d] = min(s / area * scale, invalid)
    for d in range(valid, nd):
        out[y, x, d] = invalid


@njit(inline='always')  # kernels call it (it compiles for a GPU without one)
def _pixel(i: int, h: int, w: int, nd: int, rad: int) -> tuple[int, int, int]:
    """
    Return (y, x) of pixel `i` of an (h, w) image and how many d from 0 are valid there.

    Valid: both windows inside the images. y = -1 for an i past the last pixel.
    """
    if i >= h * w:
        return -1, 0, 0
    y, x = i // w, i % w
    if rad <= y < h - rad and rad <= x < w - rad:
        return y, x, min(nd, x - rad + 1)
    return y, x, 0


def cost_volume(images: Any, max_disp: int, cost: str = 'census', window: int = 9,
                out: Any = None, scale: int = 1, dtype: type | np.dtype = np.float32) -> Any:
    """
    Return the cost volume (H, W, max_disp) of a pair on the GPU, as `cost.cost_volume`.

    `images`: float32 tensor (2, H, W) on the device, left and right: the gray images, or
    each standardized (`images.standardize`) for a cost whose spec says so. `out`: a
    contiguous tensor of the volume's shape and type to write into, or None. Returns a
    tensor on the device; ValueError for a cost without a CUDA kernel.
    """
    dtype = volume_type(cost, window, scale, dtype)
    kernel = cost_spec(cost).kernel('cuda')
    _, h, w = images.shape
    check_max_disp(max_disp, w)
    shape = (h, w, int(max_disp))
    if out is None:
        out = torch.empty(shape, dtype=gpu.VOLUME_TYPES[dtype], device=images.device)
    kernel(images, window, scale, dtype.type(max_cost(cost, window) * scale), out)
    return out


def census_volume(images: Any, window: int, scale: int, invalid: np.generic, out: Any) -> None:
    """Write Census costs into the tensor `out` (the `CostSpec.cuda` kernel of 'census')."""
    _, h, w = images.shape
    bits = torch.empty((2, 2, h, w), dtype=torch.uint64, device=images.device)
    for k in range(2):
        gpu.launch(_census_transform, h * w, images[k], window // 2, bits[k])
    gpu.launch(_census_cost, h * w, bits[0], bits[1], window // 2, int(scale), invalid, out)


def sad_volume(images: Any, window: int, scale: int, invalid: np.generic, out: Any) -> None:
    """Write SAD costs of standardized images into `out` (the `CostSpec.cuda` kernel of 'sad')."""
    gpu.launch(_sad_cost, images[0].shape[0] * images[0].shape[1], images[0], images[1],
               window // 2, np.float32(scale), invalid, out)
