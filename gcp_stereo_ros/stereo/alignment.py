"""
The residual vertical misalignment of a rectified pair, measured per frame, and its undoing.

`estimate` tracks corners of the left image into the right one (pyramidal Lucas-Kanade on
locally standardized images, so that a different exposure or lighting of the two views does
not matter), keeps the matches that track back to where they started, and fits their
vertical offsets robustly with a low-order polynomial of the position, keeping only the terms
the matches support. `correct` resamples the right image to undo it (Lanczos, so that the
resampling hardly blurs). Where the matches can not tell (too few, or they disagree), the
estimate says it is unknown and `correct` leaves the image as it is. ROS-free; the manual's
page is doc/alignment.md.
"""
from dataclasses import dataclass

import cv2
from numba import njit, prange
import numpy as np

from .images import gray_pair, to_gray

# The terms of v(x, y), each a polynomial of u = (x - cx) / cx and t = (y - cy) / cy (both -1
# at the left or top edge, +1 at the right or bottom edge), so each coefficient is in px at
# the image's edge (corner for keystone): v = offset + roll u + scale t + keystone u t
# + bow_x u^2 + bow_y t^2.
TERMS = ('offset', 'roll', 'scale', 'keystone', 'bow_x', 'bow_y')
FITTED = TERMS[:3]  # the terms `estimate` fits by default (doc/alignment.md: why not all)
CORNERS = 800  # corners tracked
WINDOW = 15  # px, side of the Lucas-Kanade window
LEVELS = 4  # pyramid levels above the image: disparities up to about 2**LEVELS * WINDOW / 2
ROUND_TRIP = 0.25  # px, largest distance from its start of a match tracked there and back
MIN_MATCHES = 40  # fewer kept matches than this: unknown
MAX_RESIDUAL = 0.35  # px, RMS of the kept matches around the fit beyond which unknown
MAX_ERROR = 0.1  # px, the largest standard error of v over the image beyond which unknown
SIGNIFICANCE = 3.0  # a term is kept where |coefficient| >= SIGNIFICANCE * its standard error
MIN_CORRECTION = 0.25  # px, largest abs(v) over the image below which `correct` resamples nothing


@dataclass(frozen=True)
class Misalignment:
    """
    Vertical offset v(x, y) of the right image against the left, px, + = right image lower.

    The left pixel (x, y) shows what the right image shows at (x - d, y + v(x - d, y)).
    `coefficients` are those of `TERMS`, px at the image's edges (0 for a term the matches
    do not support); `shape` (H, W) the image's. `left_edge` and `right_edge` are v at the
    middle of the left and right edges, `largest` the largest abs(v) over the image, `matches`
    the matches the fit kept (those within 3 robust standard deviations of it), `residual`
    the RMS of their offsets around it (px, typically 0.05-0.25), `error` the largest
    standard error of v over the image (px, typically 0.005-0.05). `known` is False when the
    pair can not tell: then `reason` says why, the coefficients are 0 and `matches`,
    `residual` and `error` are those of the failed fit (0 where it got no fit).
    """

    known: bool
    coefficients: tuple = (0.0,) * len(TERMS)
    shape: tuple = (0, 0)
    matches: int = 0
    residual: float = 0.0
    error: float = 0.0
    reason: str = ''

    def at(self, x, y):
        """Return v (px) at right-image column(s) x and row(s) y (arrays broadcast)."""
        return basis(np.asarray(x, float), np.asarray(y, float), self.shape) @ self.coefficients

    def term(self, name):
        """Return the coefficient of the term `name` of TERMS, px at the image's edge."""
        return self.coefficients[TERMS.index(name)]

    @property
    def left_edge(self):
        """Return v (px) at the middle of the left edge."""
        return float(self.at(0.0, (self.shape[0] - 1) / 2))

    @property
    def right_edge(self):
        """Return v (px) at the middle of the right edge."""
        return float(self.at(self.shape[1] - 1.0, (self.shape[0] - 1) / 2))

    @property
    def largest(self):
        """Return the largest abs(v) (px) over the image, 0 when unknown."""
        return float(np.abs(self.at(*grid(self.shape))).max()) if self.known else 0.0


def unknown(reason, shape, matches=0, residual=0.0, error=0.0):
    """Return the Misalignment that says it can not tell, and why."""
    return Misalignment(False, shape=tuple(shape), matches=matches, residual=residual,
                        error=error, reason=reason)


def basis(x, y, shape):
    """Return the values (..., 6) of the TERMS' polynomials at columns x and rows y."""
    h, w = shape
    u = (x - (w - 1) / 2) / max((w - 1) / 2, 1.0)
    t = (y - (h - 1) / 2) / max((h - 1) / 2, 1.0)
    u, t = np.broadcast_arrays(u, t)
    return np.stack([np.ones_like(u), u, t, u * t, u * u, t * t], -1)


def grid(shape, n=9):
    """Return columns and rows of an n x n grid spanning the image, edges included."""
    h, w = shape
    return np.meshgrid(np.linspace(0, w - 1, n), np.linspace(0, h - 1, n))


def standardized(gray, radius=7, sigma=1.0):
    """
    Return `gray` standardized in each (2 radius + 1)^2 square, smoothed, as uint8 (128 + 40 z).

    The local std has a floor of a twentieth of its median over the image, so flat areas stay
    flat instead of showing their noise; gain and offset that vary slowly cancel. The Gaussian
    smoothing (`sigma` px) keeps the tracker's sub-pixel estimate from locking to whole pixels.
    """
    k = (2 * radius + 1,) * 2
    d = gray - cv2.blur(gray, k)
    std = np.sqrt(cv2.blur(d * d, k))
    z = d / np.maximum(std, 0.05 * float(np.median(std)) + 1e-12)
    z = cv2.GaussianBlur(z, (0, 0), sigma)
    return np.clip(128 + 40 * z, 0, 255).astype(np.uint8)


def stretched(gray):
    """Return `gray` as uint8, its 0.5-99.5 percentile range stretched to 0-255."""
    lo, hi = np.percentile(gray, (0.5, 99.5))
    return np.clip((gray - lo) * (255.0 / max(hi - lo, 1e-12)), 0, 255).astype(np.uint8)


def corners_of(left, corners=CORNERS):
    """Return up to `corners` corners (n, 1, 2) float32 spread over the gray image `left`."""
    h, w = left.shape
    spacing = max(3, int(np.sqrt(h * w / corners) / 2))
    pts = cv2.goodFeaturesToTrack(stretched(left), corners, 0.001, spacing, blockSize=7)
    return np.empty((0, 1, 2), np.float32) if pts is None else pts


def track(sl, sr, pts, max_disp):
    """
    Return the left points (n, 2) and their right matches (n, 2), (x, y) px, float32.

    `pts` (n, 1, 2) of the standardized left image `sl` tracked into `sr` and back; kept
    where both tracks converge, the round trip ends within ROUND_TRIP px of the start, the
    match lies in the image and its disparity in [-1, max_disp).
    """
    h, w = sl.shape
    if len(pts) == 0:
        return np.empty((0, 2), np.float32), np.empty((0, 2), np.float32)
    lk = {'winSize': (WINDOW, WINDOW), 'maxLevel': LEVELS,
          'criteria': (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)}
    fwd, ok, _ = cv2.calcOpticalFlowPyrLK(sl, sr, pts, None, **lk)
    back, ok_back, _ = cv2.calcOpticalFlowPyrLK(sr, sl, fwd, None, **lk)
    p, q = pts[:, 0], fwd[:, 0]
    disp = p[:, 0] - q[:, 0]
    keep = ((ok[:, 0] == 1) & (ok_back[:, 0] == 1)
            & (np.abs(back[:, 0] - p).max(1) < ROUND_TRIP)
            & (disp > -1) & (disp < max_disp) & (q[:, 0] >= 0) & (q[:, 0] <= w - 1)
            & (q[:, 1] >= 0) & (q[:, 1] <= h - 1))
    return p[keep], q[keep]


def robust_fit(x, v, iterations=10):
    """
    Return (coefficients, inliers, sigma) of v ~ x by Tukey-biweight IRLS from the median.

    sigma is the robust (MAD) spread of the residuals, px, at least 0.02; inliers are the
    rows within 3 sigma of the fit.
    """
    coef = np.zeros(x.shape[1])
    coef[0] = np.median(v)
    for _ in range(iterations):
        r = v - x @ coef
        sigma = max(1.4826 * float(np.median(np.abs(r))), 0.02)
        u = r / (4.685 * sigma)
        sw = np.where(np.abs(u) < 1, 1 - u * u, 0.0)  # square root of the biweight
        coef = np.linalg.lstsq(x * sw[:, None], v * sw, rcond=None)[0]
    r = v - x @ coef
    sigma = max(1.4826 * float(np.median(np.abs(r))), 0.02)
    return coef, np.abs(r) < 3 * sigma, sigma


def fit(x, v, grid_basis, terms=TERMS):
    """
    Return (coefficients (6,), inliers, residual, error) with only the supported terms.

    Starting from all TERMS, the least significant term goes while any has |coefficient| <
    SIGNIFICANCE standard errors or the largest standard error of v over the image is above
    MAX_ERROR; the offset always stays. The fit is least squares over the robust fit's inliers.
    """
    terms = [TERMS.index(t) for t in TERMS if t in terms]
    while True:
        xs = x[:, terms]
        _, inl, _ = robust_fit(xs, v)
        xi, vi = xs[inl], v[inl]
        n = len(vi)
        if n < MIN_MATCHES:
            return None, inl, 0.0, 0.0
        coef = np.linalg.lstsq(xi, vi, rcond=None)[0]
        res = vi - xi @ coef
        residual = float(np.sqrt(res @ res / max(n - len(terms), 1)))
        cov = residual ** 2 * np.linalg.pinv(xi.T @ xi)
        g = grid_basis[:, terms]
        error = float(np.sqrt(np.einsum('ij,jk,ik->i', g, cov, g).max()))
        z = np.abs(coef) / np.sqrt(np.maximum(np.diag(cov), 1e-30))
        z[0] = np.inf
        if len(terms) == 1 or (z.min() >= SIGNIFICANCE and error <= MAX_ERROR):
            full = np.zeros(len(TERMS))
            full[terms] = coef
            return full, inl, residual, error
        del terms[int(np.argmin(z))]


def estimate(left, right, max_disp=256, corners=CORNERS, terms=FITTED):
    """
    Return the `Misalignment` of the rectified pair (left, right).

    Images as `StereoPipeline` takes them (gray or colour, any dtype and scale, one size);
    `max_disp` px, the largest disparity a match may have; `terms`, those of TERMS to fit.
    About 65 ms on a 1242x375 pair (2 CPU cores). Unknown, saying why, when fewer than
    MIN_MATCHES matches are kept or agree, their residual is above MAX_RESIDUAL or the fit's
    error above MAX_ERROR (a dark or textureless frame, views that show nothing alike).
    """
    left, right = gray_pair(left, right)
    shape = left.shape
    if min(shape) < 2 * WINDOW:
        return unknown(f'{shape[1]}x{shape[0]} is too small to track {WINDOW} px windows', shape)
    sl, sr = standardized(left), standardized(right)
    p, q = track(sl, sr, corners_of(left, corners), max_disp)
    if len(p) < MIN_MATCHES:
        return unknown(f'{len(p)} matches, fewer than {MIN_MATCHES}', shape, len(p))
    grid_basis = basis(*grid(shape), shape).reshape(-1, len(TERMS))
    coef, inl, residual, error = fit(basis(q[:, 0], q[:, 1], shape), q[:, 1] - p[:, 1],
                                     grid_basis, terms)
    n = int(inl.sum())
    if coef is None:
        return unknown(f'{n} of {len(p)} matches agree, fewer than {MIN_MATCHES}', shape, n)
    if residual > MAX_RESIDUAL:
        return unknown(f'matches disagree: residual {residual:.2f} px > {MAX_RESIDUAL}', shape,
                       n, residual, error)
    if error > MAX_ERROR:
        return unknown(f'uncertain: error {error:.2f} px > {MAX_ERROR}', shape, n, residual,
                       error)
    return Misalignment(True, tuple(float(c) for c in coef), tuple(shape), n, residual, error)


def lanczos_table(a=4, phases=256):
    """Return Lanczos-`a` weights (phases + 1, 2 a): row p for the fraction p / phases."""
    t = np.arange(1 - a, a + 1)[None, :] - np.linspace(0, 1, phases + 1)[:, None]
    w = np.sinc(t) * np.sinc(t / a)
    return (w / w.sum(1, keepdims=True)).astype(np.float32)


LANCZOS = lanczos_table()


@njit(inline='always')
def _phase(pos, phases):
    """Return (floor of pos, the table row of its fraction)."""
    i = int(np.floor(pos))
    return i, int((pos - i) * phases + 0.5)


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def _resample(src, coef, slope, table):
    """
    Return out[y, x] = src(x - slope (y - cy), y + v(x, y)), v the TERMS' polynomial of coef.

    Two 1-D passes of the interpolation `table` (vertical per pixel, with v taken where the
    horizontal pass will sample; then horizontal, one fraction per row); edges replicated.
    """
    h, w = src.shape
    phases, taps = table.shape[0] - 1, table.shape[1]
    first = 1 - taps // 2
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    sx, sy = max(cx, 1.0), max(cy, 1.0)
    tmp = np.empty((h, w), np.float32)
    out = np.empty((h, w), np.float32)
    for y in prange(h):
        t = (y - cy) / sy
        shift = slope * (y - cy)
        for x in range(w):
            u = (x + shift - cx) / sx
            v = coef[0] + coef[1] * u + coef[2] * t + coef[3] * u * t + coef[4] * u * u \
                + coef[5] * t * t
            i, p = _phase(y + v, phases)
            i += first
            acc = np.float32(0.0)
            if 0 <= i and i + taps <= h:
                for k in range(taps):
                    acc += table[p, k] * src[i + k, x]
            else:
                for k in range(taps):
                    acc += table[p, k] * src[min(max(i + k, 0), h - 1), x]
            tmp[y, x] = acc
    for y in prange(h):
        i, p = _phase(-slope * (y - cy), phases)
        i += first
        for x in range(w):
            acc = np.float32(0.0)
            if 0 <= x + i and x + i + taps <= w:
                for k in range(taps):
                    acc += table[p, k] * tmp[y, x + i + k]
            else:
                for k in range(taps):
                    acc += table[p, k] * tmp[y, min(max(x + i + k, 0), w - 1)]
            out[y, x] = acc
    return out


def correct(right, misalignment, min_correction=MIN_CORRECTION):
    """
    Return the right image resampled to line up with the left one, or `right` itself.

    `right`: the image the estimate was made with (any input `estimate` takes). The right
    pixel that belongs at (x, y) is (x - roll (y - cy) / cx, y + v(x, y)): v undone, and
    the roll undone as the rotation it is (its horizontal part too), by Lanczos
    interpolation (8 taps each way, which blurs far less than bilinear or bicubic), edges
    replicated; float32 gray out. Unchanged (the same object) when the estimate is unknown
    or its largest abs(v) is below `min_correction` px. About 5-10 ms at 1242x375.
    """
    m = misalignment
    if m.largest < min_correction:
        return right
    gray = to_gray(right, 'right image')
    if gray.shape != tuple(m.shape):
        raise ValueError(f'the right image is {gray.shape[1]}x{gray.shape[0]} but the '
                         f'misalignment was estimated on {m.shape[1]}x{m.shape[0]}')
    slope = m.term('roll') / max((m.shape[1] - 1) / 2, 1.0)
    return _resample(gray, np.asarray(m.coefficients, np.float32), np.float32(slope), LANCZOS)
