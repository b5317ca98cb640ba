"""Ground control points (GCPs) and the paper's cost refinement."""
from typing import Any

from numba import njit, prange
import numpy as np
import numpy.typing as npt

from .cost import UINT16_MAX


@njit(parallel=True, cache=True, nogil=True)
def _refine(cost: np.ndarray, gcp: np.ndarray, cof_d: np.ndarray, c_hi: Any, c_low: Any
            ) -> None:
    h, w, nd = cost.shape
    for y in prange(h):
        for x in range(w):
            if gcp[y, x]:
                d = cof_d[y, x]
                if 0 <= d < nd:
                    cost[y, x, d] = c_low
            else:
                cost[y, x, :] = c_hi


def right_view_agrees(disp: np.ndarray, disp_right: np.ndarray, tol: float
                      ) -> npt.NDArray[np.bool_]:
    """
    Return where the right view confirms the left disparity d = `disp` (H, W).

    That is where the right disparity `disp_right` at x - round(d) lies within `tol` of d
    (False where x - round(d) is left of the image).
    """
    w = disp.shape[1]
    xr = np.arange(w) - np.rint(disp).astype(np.int64)
    back = np.take_along_axis(disp_right, np.clip(xr, 0, w - 1), axis=1)
    return (xr >= 0) & (np.abs(back - disp) <= tol)


def select(cof_c: np.ndarray, cof_d: np.ndarray, cof_dr: np.ndarray, theta: float,
           lr_check: bool = False, plain: np.ndarray | None = None) -> npt.NDArray[np.bool_]:
    """
    Return the GCP mask: pixels whose CNN confidence `cof_c` exceeds `theta`.

    That is the paper's rule. With `lr_check` also only those whose CNN disparity d the right
    view confirms: its own CNN disparity `cof_dr` at x - d is within 1 px of d
    (`gcp_lr_check`). With `plain`, plain SGM's disparity (H, W) on the same costs without
    GCPs, also only those whose d is at most 1 px above it (`gcp_plain_check`). Both:
    doc/method.md.
    """
    if not cof_c.shape == cof_d.shape == cof_dr.shape:
        raise ValueError(f'cof_c {cof_c.shape}, cof_d {cof_d.shape} and cof_dr {cof_dr.shape} '
                         'must have one shape')
    gcp = cof_c > theta
    if lr_check:
        gcp &= right_view_agrees(cof_d, cof_dr, 1)
    if plain is not None:
        gcp &= cof_d - plain <= 1
    return gcp


def refine(cost: np.ndarray, gcp: np.ndarray, cof_d: np.ndarray, c_hi: float, c_low: float
           ) -> np.ndarray:
    """
    Refine a cost volume in place, as the paper does, and return it.

    The volume is float32, or uint16 with integer `c_hi` and `c_low`.

    Every non-GCP pixel gets `c_hi` at all disparities; a GCP keeps its costs except
    `c_low` at its CNN disparity `cof_d`.
    """
    if gcp.shape != cost.shape[:2] or cof_d.shape != cost.shape[:2]:
        raise ValueError(f'GCP mask {gcp.shape} and CNN disparity {cof_d.shape} must match '
                         f'the cost volume {cost.shape[:2]}')
    _refine(cost, np.ascontiguousarray(gcp, np.bool_), np.ascontiguousarray(cof_d, np.int32),
            *levels(cost.dtype, c_hi, c_low))
    return cost


def levels(dtype: np.dtype, c_hi: float, c_low: float) -> tuple[Any, Any]:
    """
    Return C_hi and C_low as `dtype` scalars.

    ValueError for a uint16 volume unless they are integers in [0, 65535].
    """
    dtype = np.dtype(dtype)
    if dtype == np.uint16 and not all(float(v).is_integer() and 0 <= v <= UINT16_MAX
                                      for v in (c_hi, c_low)):
        raise ValueError('a uint16 cost volume needs integer C_hi and C_low in '
                         f'[0, {UINT16_MAX}], got {c_hi}, {c_low}')
    return dtype.type(c_hi), dtype.type(c_low)


def gcp_quality(gcp: np.ndarray, cof_d: np.ndarray, gt: np.ndarray, valid: np.ndarray
                ) -> tuple[float, float]:
    """
    Return (density, accuracy) in percent.

    Density: GCPs among the evaluated pixels; accuracy: GCPs whose CNN disparity is within
    3 px of the ground truth (NaN when there is no GCP).
    """
    sel = gcp & valid
    n = int(sel.sum())
    density = 100.0 * n / max(int(valid.sum()), 1)
    accuracy = 100.0 * float((np.abs(cof_d[sel] - gt[sel]) <= 3).mean()) if n else float('nan')
    return density, accuracy
