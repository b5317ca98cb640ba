"""
The disparity confidence: how sure the pipeline is of each published disparity; ROS-free.

The probability that the published disparity is within CONFIDENCE_PX of the truth, from
what the pipeline knows of the pixel: the calibrated CNN confidence, whether it is a GCP and
its CNN disparity agrees with the final one, the SGM cost `margin` and the left-right
agreement, and these over a neighbourhood (CONFIDENCE_FEATURES). A logistic score of them,
mapped through an isotonic fit, both fitted on the validation frames (`tools.fit_confidence`)
and stored in the weights' side file (`weights.confidence_fit`), one per method.

The four confidences of the package, one name each:
- the CNN confidence `cof_c` (`cnn`): P(the CNN's disparity within 1 px), which theta cuts;
  published on the `confidence` topic;
- the disparity confidence (here; `StereoResult.disparity_confidence`, the
  `disparity_confidence` topic), which min_confidence cuts;
- `CnnConfidence` (`stages`): the CNN's outputs (cof_c, cof_d, cof_dr) of a run, which
  `StereoPipeline(..., cnn=...)` reuses;
- `ConfidenceFit` (here): the fitted map from features to the disparity confidence.
"""
from collections.abc import Iterable

import cv2
from numba import njit, prange
import numpy as np
import numpy.typing as npt

CONFIDENCE_PX = 3  # the disparity confidence is P(|d - truth| <= CONFIDENCE_PX)
CONFIDENCE_FEATURES = (
    'cnn_confidence', 'gcp', 'cnn_agrees', 'margin', 'sqrt_margin', 'lr_agrees',
    'lr_agrees_around', 'margin_around', 'log_range_around', 'log_above_min', 'log_disparity',
    'lr_agrees_wide', 'margin_wide')
WIDE = 25  # px, the square of the wider neighbourhood features
AROUND = 9  # px, the square of the neighbourhood features


def margin(s_best: np.ndarray, s_second: np.ndarray) -> np.ndarray:
    """
    Return the SGM cost margin 1 - S(winner) / S(rival), float32 in [0, 1].

    From `sgm.winners`' s_best and s_second; 1 where there is no rival or both are 0.
    OpenCV's uniqueness test with ratio u, s_second * (100 - u) >= s_best * 100, is
    margin >= u / 100.
    """
    with np.errstate(divide='ignore', invalid='ignore'):
        m = 1.0 - s_best.astype(np.float64) / s_second
    return np.where(np.isfinite(m), np.clip(m, 0.0, 1.0), 1.0).astype(np.float32)


def features(disp: np.ndarray, consistent: np.ndarray, m: np.ndarray, cof_c: np.ndarray | None,
             cof_d: np.ndarray | None, gcp: np.ndarray | None) -> npt.NDArray[np.float32]:
    """
    Return the features of each pixel, float32 (len(CONFIDENCE_FEATURES), H, W).

    `m`: the `margin`; `cof_c`, `cof_d`, `gcp` None without GCPs. Each plane is written in
    place (why: doc/notes/implementation_history.md).
    """
    planes = np.zeros((len(CONFIDENCE_FEATURES), *disp.shape), np.float32)
    (cnn, on_gcp, agrees, margin_, sqrt_margin, lr, lr_around, margin_around, spread, above,
     log_disp, lr_wide, margin_wide) = planes
    if cof_c is not None:
        cnn[:], on_gcp[:], agrees[:] = cof_c, gcp, np.abs(cof_d - disp) <= 1
    margin_[:], lr[:] = m, consistent
    np.sqrt(m, out=sqrt_margin)
    kernel = np.ones((AROUND, AROUND), np.uint8)
    low = cv2.erode(disp, kernel, borderType=cv2.BORDER_REPLICATE)
    high = cv2.dilate(disp, kernel, borderType=cv2.BORDER_REPLICATE)
    for src, dst, size in ((lr, lr_around, AROUND), (m, margin_around, AROUND),
                           (lr, lr_wide, WIDE), (m, margin_wide, WIDE)):
        cv2.blur(src, (size, size), dst=dst)
    for value, dst in ((high - low, spread), (disp - low, above), (disp, log_disp)):
        np.log1p(np.maximum(value, 0, out=dst), out=dst)
    return planes


class ConfidenceFit:
    """A fitted disparity confidence: logistic weights of the features, isotonic knots."""

    def __init__(self, coef: npt.ArrayLike, knots: Iterable[npt.ArrayLike]) -> None:
        """Take the intercept and one weight per feature, and the knots (score, P)."""
        self.coef = np.asarray(coef, np.float64)
        self.knots = tuple(np.asarray(k, np.float64) for k in knots)
        if self.coef.shape != (len(CONFIDENCE_FEATURES) + 1,) or len(self.knots[0]) < 2:
            raise ValueError(f'a confidence needs {len(CONFIDENCE_FEATURES) + 1} weights '
                             'and 2+ knots')

    def score(self, planes: np.ndarray) -> np.ndarray:
        """Return the logistic score of `features`' planes (n features, ...), float32."""
        return (np.tensordot(self.coef[1:].astype(np.float32), planes, 1)
                + np.float32(self.coef[0]))

    def __call__(self, planes: np.ndarray) -> np.ndarray:
        """Return the disparity confidence of `features`' planes, float32 (H, W) in [0, 1]."""
        return _interp(self.score(planes), *self.knots)


@njit(parallel=True, cache=True)
def _interp(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> npt.NDArray[np.float32]:
    """Return np.interp(x, xp, fp) as float32, the rows (first axis) of `x` in parallel."""
    out = np.empty(x.shape, np.float32)
    for row in prange(x.shape[0]):
        out[row] = np.interp(x[row], xp, fp)
    return out
