"""
Matching cost volumes of a rectified pair on the CPU: the dispatch and the built-in kernels.

`cost_volume` runs the CPU kernel of a registered cost (`costs.COSTS`). A volume has shape
(H, W, D) for disparities 0..D-1 and dtype float32, or uint16 fixed point for an integer
cost: the costs times an integer `scale` (10 makes C_low = 1.3 the integer 13), on which
SGM runs with exact integer arithmetic and half the memory.

A cell is valid when the matching window lies inside both images: the left window around
(x, y) and the right one around (x - d, y). Every other cell gets the cost's maximum
(`max_cost`), so SGM fills image borders from their neighbours.

Census: bit string of `neighbour < centre` over the window (window**2 - 1 bits, two uint64
words), cost = popcount(left XOR right), in [0, window**2 - 1] = [0, 80] for 9x9.

SAD: mean absolute difference over the window of the per-image standardized intensities
(each image minus its mean, divided by its std), i.e. in units of image standard
deviations, truncated at 3.2: the paper's range [0, 3.2] without rescaling.
"""
from typing import Any

from numba import njit, prange
import numpy as np

from .cancel import CancelFlag, flag_array
from .costs import cost_spec
from .images import gray_pair, standardize

UINT16_MAX = 65535

_ONE = np.uint64(1)
_M1 = np.uint64(0x5555555555555555)
_M2 = np.uint64(0x3333333333333333)
_M4 = np.uint64(0x0F0F0F0F0F0F0F0F)
_H01 = np.uint64(0x0101010101010101)


def max_cost(cost: str, window: int) -> float:
    """Return the cost assigned to invalid cells: the largest value `cost` can take."""
    return cost_spec(cost).top(window)


def check_max_disp(max_disp: int, width: int) -> None:
    """Raise ValueError unless `max_disp` is an integer in [1, width]."""
    if not (isinstance(max_disp, (int, np.integer)) and 1 <= max_disp <= width):
        raise ValueError(f'max_disp must be an integer in [1, image width {width}], '
                         f'got {max_disp!r}')


def check_window(cost: str, window: int) -> None:
    """Raise ValueError unless `window` is an odd side in the range of `cost`'s spec."""
    low, high = cost_spec(cost).windows
    if not (isinstance(window, (int, np.integer)) and not isinstance(window, bool)
            and window % 2 == 1 and low <= window <= high):
        raise ValueError(f'{cost} window must be an odd integer in [{low}, {high}], '
                         f'got {window!r}')


@njit(inline='always')
def _popcount(v: np.uint64) -> np.uint64:
    v = v - ((v >> _ONE) & _M1)
    v = (v & _M2) + ((v >> np.uint64(2)) & _M2)
    v = (v + (v >> np.uint64(4))) & _M4
    return (v * _H01) >> np.uint64(56)


@njit(parallel=True, cache=True, nogil=True)
def _census_transform(padded: np.ndarray, rad: int) -> np.ndarray:
    """
    Return the bit strings of the image inside `padded` (padded by `rad` on every side).

    They are built a neighbour offset at a time over whole rows, so the inner loop
    vectorizes.
    """
    h, w = padded.shape[0] - 2 * rad, padded.shape[1] - 2 * rad
    out = np.zeros((2, h, w), np.uint64)
    for y in prange(h):
        centre = padded[y + rad, rad:rad + w]
        k = 0
        for dy in range(-rad, rad + 1):
            for dx in range(-rad, rad + 1):
                if dy == 0 and dx == 0:
                    continue
                neighbour = padded[y + rad + dy, rad + dx:rad + dx + w]
                word = out[k // 64, y]
                shift = np.uint64(k % 64)
                for x in range(w):
                    word[x] |= np.uint64(neighbour[x] < centre[x]) << shift
                k += 1
    return out


def census_transform(gray: np.ndarray, window: int = 9) -> np.ndarray:
    """
    Return the Census bit strings of a gray image: uint64 array (2, H, W), low and high words.

    Bit k (raster order over the window, centre skipped) is 1 where that neighbour is darker
    than the centre. Outside the image the edge pixel is repeated (such cells are invalid in
    the cost volume anyway).
    """
    check_window('census', window)
    rad = window // 2
    return _census_transform(np.pad(np.asarray(gray, dtype=np.float32), rad, mode='edge'), rad)


@njit(parallel=True, cache=True, nogil=True)
def _census_cost(cl: np.ndarray, cr_rev: np.ndarray, ndisp: int, rad: int, scale: int,
                 invalid: Any, out: np.ndarray, cancel: np.ndarray) -> None:
    """`cr_rev`: the right bit strings with each row reversed (see `cost_volume`)."""
    h, w = cl.shape[1], cl.shape[2]
    for y in prange(h):
        if cancel[0]:
            continue
        row_ok = rad <= y < h - rad
        right_lo = cr_rev[0, y]
        right_hi = cr_rev[1, y]
        for x in range(w):
            # d <= x - rad
            nvalid = min(ndisp, x - rad + 1) if row_ok and rad <= x < w - rad else 0
            lo = cl[0, y, x]
            hi = cl[1, y, x]
            r_lo = right_lo[w - 1 - x:]  # r_lo[d] = right word at x - d
            r_hi = right_hi[w - 1 - x:]
            cell = out[y, x]
            for d in range(nvalid):
                cell[d] = (_popcount(lo ^ r_lo[d]) + _popcount(hi ^ r_hi[d])) * scale
            for d in range(nvalid, ndisp):
                cell[d] = invalid


@njit(parallel=True, cache=True, nogil=True)
def _sad_cost(left: np.ndarray, right_rev: np.ndarray, ndisp: int, rad: int, scale: Any,
              invalid: Any, out: np.ndarray, cancel: np.ndarray) -> None:
    """`right_rev`: the right image with each row reversed (see `cost_volume`)."""
    h, w = left.shape
    area = np.float32((2 * rad + 1) ** 2)
    for y in prange(h):
        if cancel[0]:
            continue
        if y < rad or y >= h - rad:
            out[y] = invalid
            continue
        col = np.zeros((w, ndisp), np.float32)  # column sums of |L - R| over the window rows
        for yy in range(y - rad, y + rad + 1):
            for x in range(w):
                lv = left[yy, x]
                r = right_rev[yy, w - 1 - x:]  # r[d] = right[yy, x - d]
                c = col[x]
                for d in range(min(ndisp, x + 1)):
                    c[d] += abs(lv - r[d])
        acc = np.zeros(ndisp, np.float32)  # window sum, slid along the row
        for x in range(min(rad, w)):
            for d in range(ndisp):
                acc[d] += col[x, d]
        for x in range(w):
            if x + rad < w:
                for d in range(ndisp):
                    acc[d] += col[x + rad, d]
            if x - rad - 1 >= 0:
                for d in range(ndisp):
                    acc[d] -= col[x - rad - 1, d]
            nvalid = min(ndisp, x - rad + 1) if rad <= x < w - rad else 0  # d <= x - rad
            cell = out[y, x]
            for d in range(nvalid):
                cell[d] = min(acc[d] / area * scale, invalid)
            for d in range(nvalid, ndisp):
                cell[d] = invalid


def output_array(out: np.ndarray | None, shape: tuple[int, ...],
                 dtype: type | np.dtype = np.float32) -> np.ndarray:
    """
    Return `out` if it is a C-contiguous `dtype` array of `shape`, a new one if `out` is None.

    Streaming callers pass the array of the previous frame back: a fresh (H, W, D) volume
    costs a page fault per 4 KiB on first touch (a KITTI volume is 238 MB).
    """
    if out is None:
        return np.empty(shape, dtype)
    if out.shape != shape or out.dtype != dtype or not out.flags.c_contiguous:
        raise ValueError(f'out must be a C-contiguous {np.dtype(dtype)} array of shape {shape}, '
                         f'got {out.dtype} {out.shape}')
    return out


def volume_type(cost: str, window: int, scale: int, dtype: type | np.dtype) -> np.dtype:
    """
    Return `dtype` as a numpy dtype if a `cost` volume times `scale` can be held in it.

    That is float32, or uint16 for an integer cost (`CostSpec.integer`) whose largest cost
    times `scale` fits in 16 bits; ValueError otherwise, or for a bad window or a `scale`
    that is not an integer >= 1.
    """
    check_window(cost, window)
    if not (isinstance(scale, (int, np.integer)) and not isinstance(scale, bool) and scale >= 1):
        raise ValueError(f'scale must be an integer >= 1, got {scale!r}')
    dtype = np.dtype(dtype)
    if dtype == np.uint16:
        if not cost_spec(cost).integer:
            raise ValueError(f'uint16 volumes hold integer costs only ({cost} costs are '
                             'fractional)')
        if max_cost(cost, window) * scale > UINT16_MAX:
            raise ValueError(f'{cost} costs up to {max_cost(cost, window):g} times scale {scale} '
                             'do not fit in 16 bits')
    elif dtype != np.float32:
        raise ValueError(f'dtype must be float32 or uint16, got {dtype}')
    return dtype


def cost_volume(left: np.ndarray, right: np.ndarray, max_disp: int, cost: str = 'census',
                window: int = 9, out: np.ndarray | None = None, scale: int = 1,
                dtype: type | np.dtype = np.float32,
                cancel: CancelFlag | None = None) -> np.ndarray:
    """
    Return the matching cost volume (H, W, max_disp) of a rectified pair (see module doc).

    `cost` names a registered cost (`costs.COSTS`); each cost is multiplied by the integer
    `scale`; the volume is in `dtype`: float32, or uint16 for an integer cost.

    `left`, `right`: same-size gray or RGB arrays (uint8, uint16 or float). `out`: an array
    to write the volume into (see `output_array`). `cancel`: a CancelFlag; once set, the
    remaining rows are skipped (the volume is then incomplete: check the flag).
    """
    dtype = volume_type(cost, window, scale, dtype)
    spec = cost_spec(cost)
    lg, rg = gray_pair(left, right)
    check_max_disp(max_disp, lg.shape[1])
    if spec.standardized:
        lg, rg = standardize(lg), standardize(rg)
    out = output_array(out, lg.shape + (int(max_disp),), dtype)
    spec.kernel('cpu')(lg, rg, int(max_disp), window, scale,
                       dtype.type(max_cost(cost, window) * scale), out, flag_array(cancel))
    return out


# Both kernels read the right rows reversed: at w - 1 - x + d lies the right pixel x - d, so
# d = 0, 1, ... is a forward run, and their inner loops vectorize.

def census_volume(left: np.ndarray, right: np.ndarray, max_disp: int, window: int, scale: int,
                  invalid: np.generic, out: np.ndarray, cancel: np.ndarray) -> None:
    """Write Census costs into `out` (the `CostSpec.cpu` kernel of 'census')."""
    right_rev = np.ascontiguousarray(census_transform(right, window)[:, :, ::-1])
    _census_cost(census_transform(left, window), right_rev, max_disp, window // 2, int(scale),
                 invalid, out, cancel)


def sad_volume(left: np.ndarray, right: np.ndarray, max_disp: int, window: int, scale: int,
               invalid: np.generic, out: np.ndarray, cancel: np.ndarray) -> None:
    """Write SAD costs of standardized images into `out` (the `CostSpec.cpu` kernel of 'sad')."""
    _sad_cost(left, np.ascontiguousarray(right[:, ::-1]), max_disp, window // 2,
              np.float32(scale), invalid, out, cancel)
