"""KITTI-style disparity error rates: dense (as a submission is scored) and of published pixels."""
from numba import njit
import numpy as np
from numpy.typing import ArrayLike

from ..stereo.postprocess import fill_rows

THRESHOLDS = (1, 2, 3, 5)


@njit(cache=True)
def _fill_columns(d: np.ndarray) -> None:
    """Give each column's non-finite ends its nearest finite value, in place."""
    h, w = d.shape
    for u in range(w):
        for v in range(h):  # to the top
            if np.isfinite(d[v, u]):
                d[:v, u] = d[v, u]
                break
        for v in range(h - 1, -1, -1):  # and to the bottom
            if np.isfinite(d[v, u]):
                d[v + 1:, u] = d[v, u]
                break


def interpolate_background(disp: ArrayLike) -> np.ndarray:
    """
    Return `disp` with its invalid (non-finite) pixels filled as the KITTI devkit does.

    The devkit's `interpolateBackground` (what a sparse KITTI submission is scored on): in
    each row a gap between two valid pixels gets the smaller of their disparities (the
    background), gaps at a row's ends the nearest valid value; then each column's invalid
    ends take its nearest valid value. Rows and columns without any valid pixel stay NaN.
    """
    d = np.array(disp, dtype=np.float64)
    fill_rows(d)
    _fill_columns(d)
    return d


def error_rates(disp: ArrayLike, gt: ArrayLike,
                valid: ArrayLike | None = None) -> dict[str, float]:
    """
    Return the bad-pixel rates, mean absolute error and density of `disp` against `gt`.

    Evaluated pixels are `valid` (default: all) where `gt` is finite; published pixels are
    those of them where `disp` is finite. `bad1`..`bad5`: the percentages of evaluated
    pixels with |d - gt| above 1, 2, 3, 5 px, `disp` first filled by
    `interpolate_background` as KITTI scores a sparse submission (equal to the rates of
    `disp` itself when it is dense); `density`: % of evaluated pixels published;
    `bad1_published`..`bad5_published`: the rates among published pixels; `near3_published`:
    % of published pixels more than 3 px too near (d - gt > 3, phantom obstacles); `mae`:
    mean |d - gt| in px over published pixels. Rates over no pixel are NaN.
    """
    disp = np.asarray(disp, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if disp.shape != gt.shape:
        raise ValueError(f'disparity has shape {disp.shape} but ground truth has {gt.shape}')
    mask = np.isfinite(gt)
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != gt.shape:
            raise ValueError(f'valid mask has shape {valid.shape} but ground truth has {gt.shape}')
        mask &= valid
    if not mask.any():
        raise ValueError('no pixel to evaluate: '
                         'the valid mask and finite ground truth do not overlap')
    published = np.isfinite(disp[mask])
    dense = interpolate_background(disp) if not published.all() else disp
    err = np.abs(dense[mask] - gt[mask])
    err[~np.isfinite(err)] = np.inf  # no valid pixel in its row or column to fill it from
    rates = {f'bad{t}': 100.0 * float(np.mean(err > t)) for t in THRESHOLDS}
    signed = disp[mask][published] - gt[mask][published]
    rates['density'] = 100.0 * float(published.mean())

    def share(wrong: np.ndarray) -> float:
        return 100.0 * float(wrong.mean()) if wrong.size else float('nan')
    for t in THRESHOLDS:
        rates[f'bad{t}_published'] = share(np.abs(signed) > t)
    rates['near3_published'] = share(signed > 3)
    rates['mae'] = float(np.abs(signed).mean()) if signed.size else float('nan')
    return rates


def sparsification(wrong: ArrayLike, score: ArrayLike,
                   steps: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """
    Return (fractions, rates): the sparsification curve of a confidence `score`.

    `rates[i]`: % of `wrong` (bool per pixel) among the `fractions[i]` most confident pixels
    (highest `score`), for fractions 1/steps, 2/steps, ..., 1. The lower and flatter, the
    better the score ranks; with the error itself as the score it is the oracle's curve.
    """
    wrong = np.asarray(wrong, bool).ravel()
    if wrong.size == 0:
        raise ValueError('no pixel to rank')
    order = np.argsort(-np.asarray(score, np.float64).ravel(), kind='stable')
    hits = np.cumsum(wrong[order])
    fractions = np.arange(1, steps + 1) / steps
    k = np.maximum(1, np.round(fractions * wrong.size).astype(np.int64))
    return fractions, 100.0 * hits[k - 1] / k


def sparsification_area(fractions: np.ndarray, rates: np.ndarray) -> float:
    """Return the area under a sparsification curve (% x fraction; from fraction 0 on)."""
    return float(np.trapezoid(np.concatenate([[rates[0]], rates]),
                              np.concatenate([[0.0], fractions])))
