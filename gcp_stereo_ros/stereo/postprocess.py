"""
What of the winner-takes-all disparity to publish: the invalidation; ROS-free.

`invalidate` marks NaN, in this order, the pixels
- where the search was cut short (`valid_window`): within window // 2 of the image's edge
  (the matching window leaves the image), and in the left band where fewer than max_disp
  candidates exist (x < max_disp - 1: only d <= x was searched), where the winner lies at
  the end of its range (d >= x - 1, so the minimum may lie beyond the range); a winner
  inside its range is kept;
- that fail the left-right check (`lr_check`: the right view's winner at x - d is more than
  1 px from d);
- that fail the uniqueness test (`uniqueness_ratio` u, OpenCV's uniquenessRatio): invalid
  where a disparity more than 1 px from the winner has S(d) * (100 - u) < S(winner) * 100;
- whose depth is below `min_depth` or beyond `max_depth` metres (with a camera model);
- whose disparity confidence (`disparity_confidence`) is below `min_confidence` and
  whose background fits (`background_ratio` r): a pixel's background is the smaller
  disparity of the nearest pixels left and right in its row that stay (published and at
  least min_confidence), what the KITTI devkit's interpolation fills a gap with; it fits
  where its summed SGM cost (the least at its rounded disparity and 1 px either side) is at
  most r times the winner's.
  A pixel whose costs rule its background out, a low-confidence object standing in front
  of its row, keeps its disparity; with r = 0 every pixel below min_confidence goes;
- in speckles (OpenCV's filterSpeckles with stereo_image_proc's meaning): connected regions
  of at most `speckle_size` pixels, neighbours within `speckle_range` px of each other;
- more than `plain_check` px nearer than plain SGM, the same costs aggregated without the
  GCPs: a second opinion without the CNN, last, so that the tests before it do not see the
  gaps it leaves.
A value of 0 (False) turns each off; why each test and its default: doc/published.md.
`cuda.postprocess.invalidate` is the twin on a GPU: from the same inputs (`sgm.winners`,
`cuda.sgm.winners`) the same pixels. With `downsample` f everything here runs on the
matching grid, 1 / f of the images, before the result is blown up to full size: the sizes
and disparities the parameters give in full-size pixels are scaled to it (a speckle of
`speckle_size` / f^2 matching pixels, `speckle_range` / f).
"""
from collections.abc import Callable

import cv2
from numba import njit
import numpy as np
import numpy.typing as npt

from .config import StereoConfig

SPECKLE_SCALE = 16  # fixed-point steps per pixel of filterSpeckles' int16 disparity (OpenCV's)
# The summed SGM costs of pixels (rows, cols) at disparities (n, k): `background_fits`.
Costs = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def valid_window(cfg: StereoConfig, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """
    Return the region (x0, y0, x1, y1) where the matching window stays inside the image.

    In full-size pixels when matched at 1 / cfg.downsample; empty for images too small.
    """
    return inside(cfg.window // 2 * cfg.downsample, shape)


def inside(border: int, shape: tuple[int, ...]) -> tuple[int, int, int, int]:
    """Return the region (x0, y0, x1, y1) of `shape` (H, W) at least `border` px from its edges."""
    h, w = shape
    x0, y0 = min(border, w), min(border, h)
    return x0, y0, max(w - border, x0), max(h - border, y0)


def cut_short(disp: np.ndarray, cfg: StereoConfig) -> npt.NDArray[np.bool_]:
    """
    Return where the search was cut short (see the module's docstring), bool (h, w).

    `disp`: on the matching grid (1 / cfg.downsample of the images), in its pixels.
    """
    x0, y0, x1, y1 = inside(cfg.window // 2, disp.shape)
    out = np.ones(disp.shape, bool)
    out[y0:y1, x0:x1] = False
    x = np.arange(disp.shape[1])
    with np.errstate(invalid='ignore'):
        out |= (x < cfg.matched_disp - 1) & (x - disp <= 1)
    return out


def depth_limits(cfg: StereoConfig, camera: tuple[float, float] | None
                 ) -> tuple[float, float] | None:
    """
    Return (lowest, highest) disparity of depths within [min_depth, max_depth], or None.

    `camera`: (f * T in px m, cx_left - cx_right in px) with Z = f T / (d - offset); None
    (no calibration) applies no limit.
    """
    if camera is None or not (cfg.min_depth or cfg.max_depth):
        return None
    ft, offset = camera
    high = ft / cfg.min_depth + offset if cfg.min_depth else np.inf
    low = ft / cfg.max_depth + offset if cfg.max_depth else -np.inf
    return low, high


def speckles(disp: np.ndarray, size: float, max_diff: float) -> npt.NDArray[np.bool_]:
    """Return a mask of the pixels of `disp` that lie in speckles, as the module says."""
    invalid = -SPECKLE_SCALE
    fixed = np.where(np.isfinite(disp), np.rint(disp * SPECKLE_SCALE), invalid)
    fixed = np.clip(fixed, invalid, np.iinfo(np.int16).max).astype(np.int16)
    filtered, _ = cv2.filterSpeckles(fixed, invalid, int(size), int(max_diff * SPECKLE_SCALE))
    return (filtered == invalid) & np.isfinite(disp)


@njit(cache=True)
def fill_rows(d: np.ndarray) -> None:
    """
    Fill each row's non-finite pixels of `d` in place, as the KITTI devkit's interpolation does.

    A gap between two finite pixels takes the smaller of their disparities (the background),
    a gap at a row's end the one finite pixel beside it; a row without one stays as it is.
    """
    h, w = d.shape
    for y in range(h):
        last = -1  # the column of the last finite pixel
        for x in range(w):
            if not np.isfinite(d[y, x]):
                continue
            if last < x - 1:
                d[y, last + 1:x] = d[y, x] if last < 0 else min(d[y, last], d[y, x])
            last = x
        if 0 <= last < w - 1:
            d[y, last + 1:] = d[y, last]


def backgrounds(disp: np.ndarray, low: np.ndarray) -> npt.NDArray[np.float32]:
    """
    Return each `low` pixel's background disparity, float32 (h, w), NaN elsewhere.

    The smaller disparity of the nearest pixels left and right in its row that are finite
    and not `low` (at a row's end the one there is; NaN where its row has none): `fill_rows`
    of the pixels that stay.
    """
    out = np.where(low, np.float32(np.nan), disp).astype(np.float32)
    fill_rows(out)
    out[~low] = np.nan
    return out


@njit(cache=True)
def _lookups(disp: np.ndarray, b: np.ndarray, top: int
             ) -> tuple[np.ndarray, np.ndarray, npt.NDArray[np.intp]]:
    """
    Return rows, cols (n,) and disparities (n, 4) of the pixels with a background `b`.

    The disparities: the background's, rounded, 1 px either side of it, and the winner's,
    each clipped to [0, top].
    """
    rows, cols = np.nonzero(np.isfinite(b))
    out: np.ndarray = np.empty((len(rows), 4), np.intp)
    for i in range(len(rows)):
        at = np.intp(np.rint(b[rows[i], cols[i]]))
        for j in range(3):
            out[i, j] = min(max(at + j - 1, 0), top)
        out[i, 3] = min(max(np.intp(np.rint(disp[rows[i], cols[i]])), 0), top)
    return rows, cols, out


def background_fits(disp: np.ndarray, low: np.ndarray, costs: Costs, cfg: StereoConfig
                    ) -> npt.NDArray[np.bool_]:
    """
    Return where a `low` pixel's background fits within cfg.background_ratio, bool (h, w).

    See the module's docstring. `costs(rows, cols, disparities)` gives the summed SGM costs
    of the pixels (rows[i], cols[i]) at disparities[i, :] in [0, cfg.matched_disp - 1],
    (n,) (n,) (n, k) intp -> (n, k) (`sgm.costs_at` of the summed costs); a low
    pixel without a background fits.
    """
    rows, cols, at = _lookups(disp, backgrounds(disp, low), cfg.matched_disp - 1)
    s = costs(rows, cols, at).astype(np.float64)
    background = np.minimum(np.minimum(s[:, 0], s[:, 1]), s[:, 2])  # faster than .min(1)
    kept = background > cfg.background_ratio * s[:, 3]
    fits = low.copy()
    fits[rows[kept], cols[kept]] = False
    return fits


def invalidate(disp: np.ndarray, consistent: np.ndarray, m: np.ndarray, cfg: StereoConfig,
               camera: tuple[float, float] | None = None,
               disparity_confidence: np.ndarray | None = None, costs: Costs | None = None,
               plain: np.ndarray | None = None) -> np.ndarray:
    """
    Set NaN in `disp` (float32, in place) where cfg's tests fail; return `disp`.

    Every array is on the matching grid (1 / cfg.downsample of the images), `disp` in its
    pixels; the depth limits, the speckle size and range and `plain_check`, given for the
    full-size images, are scaled to it. `m`: the `margin`; `disparity_confidence`
    (float32) for `min_confidence`, None if there is none (then it is not applied);
    `costs`: the summed SGM costs for `background_ratio` (see `background_fits`), None:
    every pixel below min_confidence goes; `plain`: plain SGM's disparity for
    `plain_check`, None without GCPs (then it is not applied).
    """
    f = cfg.downsample
    if cfg.valid_window:
        disp[cut_short(disp, cfg)] = np.nan
    if cfg.lr_check:
        disp[~consistent] = np.nan
    if cfg.uniqueness_ratio:
        disp[m < np.float32(cfg.uniqueness_ratio / 100)] = np.nan
    limits = depth_limits(cfg, camera)
    if limits is not None:
        low, high = (np.float32(limit / f) for limit in limits)
        with np.errstate(invalid='ignore'):
            disp[(disp < low) | (disp > high)] = np.nan
    if cfg.min_confidence and disparity_confidence is not None:
        unsure = disparity_confidence < cfg.min_confidence
        if cfg.background_ratio and costs is not None:
            unsure = background_fits(disp, unsure & np.isfinite(disp), costs, cfg)
        disp[unsure] = np.nan
    size = cfg.speckle_size // f ** 2
    if size:
        disp[speckles(disp, size, cfg.speckle_range / f)] = np.nan
    if cfg.plain_check and plain is not None:
        with np.errstate(invalid='ignore'):
            disp[disp - plain > np.float32(cfg.plain_check / f)] = np.nan
    return disp
