"""KITTI-style disparity error rates."""
import numpy as np

THRESHOLDS = (1, 2, 3, 5)


def error_rates(disp, gt, valid=None):
    """
    Return the bad-pixel rates and mean absolute error of `disp` against `gt`.

    Evaluated pixels are `valid` (default: all) where `gt` is finite. `bad1`..`bad5` are the
    percentages of them with |disp - gt| above 1, 2, 3, 5 px, counting pixels without an
    estimate (NaN or inf in `disp`) as errors; `mae` is the mean |disp - gt| in px over the
    evaluated pixels that have an estimate (NaN if none has).
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
    err = np.abs(disp[mask] - gt[mask])
    estimated = np.isfinite(err)
    err[~estimated] = np.inf
    rates = {f'bad{t}': 100.0 * float(np.mean(err > t)) for t in THRESHOLDS}
    rates['mae'] = float(err[estimated].mean()) if estimated.any() else float('nan')
    return rates
