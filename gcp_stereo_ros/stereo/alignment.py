"""
The residual vertical misalignment of a rectified pair, measured per frame, and its undoing.

`estimate` tracks corners of the left image into the right one (pyramidal Lucas-Kanade on
locally standardized images, so that a different exposure or lighting of the two views does
not matter), keeps the matches that track back to where they started, and fits their
vertical offsets robustly with a low-order polynomial of the position; a term counts only
where it is well above its standard error. `correct` resamples the right image to undo it
(Lanczos, so that the resampling hardly blurs) and leaves it alone below MIN_CORRECTION px.
Where the matches can not tell (a dark or textureless pair, too few matches, or they
disagree) the estimate is unknown, says why, and nothing changes. ROS-free; the manual's
page is doc/alignment.md.
"""
from dataclasses import dataclass
from typing import Any

import cv2
from numba import njit, prange
import numpy as np
import numpy.typing as npt

from .images import gray_pair, to_gray

Array = npt.NDArray[np.floating[Any]]
Image = npt.NDArray[np.float32]

# The terms of v(x, y), each a polynomial of u = (x - cx) / cx and t = (y - cy) / cy (both -1
# at the left or top edge, +1 at the right or bottom edge), so each coefficient is in px at
# the image's edge (corner for keystone): v = offset + roll u + scale t + keystone u t
# + bow_x u^2 + bow_y t^2.
TERMS = ('offset', 'roll', 'scale', 'keystone', 'bow_x', 'bow_y')
FITTED = TERMS[:3]  # the terms `estimate` fits by default (doc/alignment.md: why these)
CORNERS = 800  # corners tracked
WINDOW = 15  # px, side of the Lucas-Kanade window
LEVELS = 4  # pyramid levels above the image: disparities up to about 2**LEVELS * WINDOW / 2
ROUND_TRIP = 0.25  # px, largest distance from its start of a match tracked there and back
MIN_MATCHES = 40  # fewer kept matches than this: unknown
MAX_RESIDUAL = 0.35  # px, RMS of the kept matches around the fit beyond which unknown
MAX_ERROR = 0.1  # px, the largest standard error of v over the image beyond which unknown
SIGNIFICANCE = 3.0  # a term counts where |coefficient| >= SIGNIFICANCE * its standard error
MIN_CORRECTION = 0.25  # px, largest abs(v) over the image below which nothing is resampled
MAX_CORRECTION = 8.0  # px, largest abs(v) beyond which the pair is not corrected: recalibrate
DARK = 16  # grey levels: an integer image whose 99.5th percentile is below is dark
CAUSES = ('none', 'small', 'dark', 'textureless', 'saturated', 'few matches', 'disagree',
          'uncertain')
ZEROS = (0.0,) * len(TERMS)


@dataclass(frozen=True)
class Misalignment:
    """
    Vertical offset v(x, y) of the right image against the left, px, + = right image lower.

    The left pixel (x, y) shows what the right image shows at (x - d, y + v(x - d, y)).
    `fitted` holds the least-squares coefficient of each of `TERMS` (px at the image's
    edges, 0 where not fitted) and `errors` their standard errors (0: exact, as for a
    coefficient set by hand); `coefficients` keeps those with abs(fitted) >= SIGNIFICANCE *
    error (the others 0): the field `at`, `largest` and `correct` use. `shape` (H, W) is the
    image's, `matches` the matches the fit kept (within 3 robust standard deviations),
    `residual` their RMS around it (px, typically 0.05-0.25), `error` the largest standard
    error of the used field over the image (px, typically 0.005-0.05). `known` is False when
    the pair can not tell: `cause` (one of CAUSES; 'none': nothing measured yet) and
    `reason` say why, the coefficients are 0, `matches` and `residual` those of the failed
    fit (0 where it got none).
    """

    known: bool
    fitted: tuple[float, ...] = ZEROS
    errors: tuple[float, ...] = ZEROS
    shape: tuple[int, int] = (0, 0)
    matches: int = 0
    residual: float = 0.0
    error: float = 0.0
    reason: str = ''
    cause: str = ''

    @property
    def coefficients(self) -> tuple[float, ...]:
        """Return the coefficient of each of TERMS that the data supports, else 0 (px)."""
        return tuple(c if abs(c) >= SIGNIFICANCE * e else 0.0
                     for c, e in zip(self.fitted, self.errors))

    def at(self, x: npt.ArrayLike, y: npt.ArrayLike) -> Array:
        """Return v (px) at right-image column(s) x and row(s) y (arrays broadcast)."""
        return basis(np.asarray(x, float), np.asarray(y, float), self.shape) @ np.asarray(
            self.coefficients)

    def term(self, name: str) -> float:
        """Return the supported coefficient of the term `name` of TERMS, px at the edge."""
        return self.coefficients[TERMS.index(name)]

    @property
    def left_edge(self) -> float:
        """Return v (px) at the middle of the left edge."""
        return float(self.at(0.0, (self.shape[0] - 1) / 2))

    @property
    def right_edge(self) -> float:
        """Return v (px) at the middle of the right edge."""
        return float(self.at(self.shape[1] - 1.0, (self.shape[0] - 1) / 2))

    @property
    def largest(self) -> float:
        """Return the largest abs(v) (px) over the image, 0 when unknown."""
        return float(np.abs(self.at(*grid(self.shape))).max()) if self.known else 0.0

    def verdict(self, min_correction: float = MIN_CORRECTION,
                max_correction: float = MAX_CORRECTION) -> str:
        """Return what `correct` does with it: 'corrected', 'below ...', 'too large ...'."""
        if not self.known:
            return f'unknown ({self.cause}: {self.reason})'
        if self.largest < min_correction:
            return f'below {min_correction:g} px: not resampled'
        if self.largest > max_correction:
            return f'too large (over {max_correction:g} px): not corrected, recalibrate'
        return 'corrected'

    def summary(self) -> str:
        """Return one line: the largest offset and the supported terms, or why unknown."""
        if not self.known:
            return f'misalignment unknown: {self.reason}'
        terms = ', '.join(f'{n} {c:+.2f}' for n, c in zip(TERMS, self.coefficients) if c)
        return (f'misalignment {self.largest:.2f} px ({terms or "no term supported"}; '
                f'{self.matches} matches, residual {self.residual:.2f} px)')


def unknown(cause: str, reason: str, shape: tuple[int, ...], matches: int = 0,
            residual: float = 0.0, error: float = 0.0) -> Misalignment:
    """Return the Misalignment that says it can not tell: `cause` of CAUSES, and why."""
    return Misalignment(False, shape=(int(shape[0]), int(shape[1])), matches=matches,
                        residual=residual, error=error, reason=reason, cause=cause)


def basis(x: Array, y: Array, shape: tuple[int, ...]) -> Array:
    """Return the values (..., 6) of the TERMS' polynomials at columns x and rows y."""
    h, w = shape[:2]
    u = (x - (w - 1) / 2) / max((w - 1) / 2, 1.0)
    t = (y - (h - 1) / 2) / max((h - 1) / 2, 1.0)
    u, t = np.broadcast_arrays(u, t)
    return np.stack([np.ones_like(u), u, t, u * t, u * u, t * t], -1)


def grid(shape: tuple[int, ...], n: int = 9) -> tuple[Array, Array]:
    """Return columns and rows of an n x n grid spanning the image, edges included."""
    h, w = shape[:2]
    x, y = np.meshgrid(np.linspace(0, w - 1, n), np.linspace(0, h - 1, n))
    return x, y


def standardized(gray: Image, radius: int = 7, sigma: float = 1.0) -> npt.NDArray[np.uint8]:
    """
    Return `gray` standardized in each (2 radius + 1)^2 square, smoothed, as uint8 (128 + 40 z).

    The local std has a floor of a twentieth of its median over the image, so flat areas stay
    flat instead of showing their noise; gain and offset that vary slowly cancel. The Gaussian
    smoothing (`sigma` px) keeps the tracker's sub-pixel estimate from locking to whole pixels.
    """
    k = (2 * radius + 1,) * 2
    d = gray - cv2.blur(gray, k)
    std = np.sqrt(np.maximum(cv2.blur(d * d, k), 0))  # the box sums may round below 0
    z = cv2.GaussianBlur(d / np.maximum(std, 0.05 * float(np.median(std)) + 1e-12), (0, 0),
                         sigma)
    return np.clip(128 + 40 * z, 0, 255).astype(np.uint8)


def stretched(gray: Image) -> npt.NDArray[np.uint8]:
    """Return `gray` as uint8, its 0.5-99.5 percentile range stretched to 0-255."""
    lo, hi = np.percentile(gray, (0.5, 99.5))
    return np.clip((gray - lo) * (255.0 / max(hi - lo, 1e-12)), 0, 255).astype(np.uint8)


def dark(gray: Image) -> bool:
    """Return whether `gray` holds integer grey levels with its 99.5th percentile below DARK."""
    sample = gray[::7, ::7]
    return bool(np.all(sample == np.round(sample)) and np.percentile(sample, 99.5) < DARK)


def clipped(lg: Image, rg: Image) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """
    Return where each image is within half a window of its maximum, if they saturate apart.

    The edge of a saturated area lies where the scene crosses the sensor's limit, which moves
    with the exposure: where one view has over twice the other's share of pixels at its
    maximum (KITTI's views, one exposure: within 1.5 times), the areas near it hold no
    match; otherwise (and for a `dark` image) nothing is masked.
    """
    top = [(g >= g.max()) & (not dark(g)) for g in (lg, rg)]
    share = sorted(float(t.mean()) for t in top)
    if share[1] <= 2 * share[0] + 0.001:
        return np.zeros(lg.shape, bool), np.zeros(rg.shape, bool)
    near = [cv2.dilate(t.astype(np.uint8), np.ones((WINDOW, WINDOW), np.uint8)).astype(bool)
            for t in top]
    return near[0], near[1]


def corners_of(left: Image, corners: int = CORNERS) -> npt.NDArray[np.float32]:
    """Return up to `corners` corners (n, 1, 2) float32 spread over the gray image `left`."""
    h, w = left.shape
    spacing = max(3, int(np.sqrt(h * w / corners) / 2))
    pts = cv2.goodFeaturesToTrack(stretched(left), corners, 0.001, spacing, blockSize=7)
    return np.empty((0, 1, 2), np.float32) if pts is None else np.asarray(pts, np.float32)


def track(sl: npt.NDArray[np.uint8], sr: npt.NDArray[np.uint8], pts: npt.NDArray[np.float32],
          max_disp: int, clipped_l: npt.NDArray[np.bool_], clipped_r: npt.NDArray[np.bool_]
          ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """
    Return the left points (n, 2) and their right matches (n, 2), (x, y) px, float32.

    `pts` (n, 1, 2) of the standardized left image `sl` tracked into `sr` and back; kept
    where both tracks converge, the round trip ends within ROUND_TRIP px of the start, the
    match lies in the image, its disparity in [-1, max_disp) and neither end in its image's
    `clipped` area (`clipped_l`, `clipped_r`).
    """
    h, w = sl.shape
    pts = pts[~clipped_l[pts[:, 0, 1].astype(int), pts[:, 0, 0].astype(int)]]
    if len(pts) == 0:
        return np.empty((0, 2), np.float32), np.empty((0, 2), np.float32)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    fwd, ok, _ = cv2.calcOpticalFlowPyrLK(sl, sr, pts, pts.copy(), winSize=(WINDOW, WINDOW),
                                          maxLevel=LEVELS, criteria=crit)
    back, ok_back, _ = cv2.calcOpticalFlowPyrLK(sr, sl, fwd, fwd.copy(), winSize=(WINDOW, WINDOW),
                                                maxLevel=LEVELS, criteria=crit)
    p, q = pts[:, 0], np.asarray(fwd, np.float32)[:, 0]
    back = np.asarray(back, np.float32)
    disp = p[:, 0] - q[:, 0]
    keep = ((ok[:, 0] == 1) & (ok_back[:, 0] == 1)
            & (np.abs(back[:, 0] - p).max(1) < ROUND_TRIP)
            & (disp > -1) & (disp < max_disp) & (q[:, 0] >= 0) & (q[:, 0] <= w - 1)
            & (q[:, 1] >= 0) & (q[:, 1] <= h - 1))
    p, q = p[keep], q[keep]
    inside = ~clipped_r[np.round(q[:, 1]).astype(int), np.round(q[:, 0]).astype(int)]
    return p[inside], q[inside]


def robust_fit(x: Array, v: Array, iterations: int = 10) -> tuple[Array, npt.NDArray[np.bool_]]:
    """
    Return (coefficients, inliers) of v ~ x by Tukey-biweight IRLS from the median.

    Inliers are the rows within 3 robust (MAD) standard deviations of the fit, that
    spread taken at least 0.02 px.
    """
    coef: Array = np.zeros(x.shape[1])
    coef[0] = np.median(v)
    for _ in range(iterations):
        r = v - x @ coef
        sigma = max(1.4826 * float(np.median(np.abs(r))), 0.02)
        u = r / (4.685 * sigma)
        sw = np.where(np.abs(u) < 1, 1 - u * u, 0.0)  # square root of the biweight
        coef = np.linalg.lstsq(x * sw[:, None], v * sw, rcond=None)[0]
    r = v - x @ coef
    sigma = max(1.4826 * float(np.median(np.abs(r))), 0.02)
    return coef, np.abs(r) < 3 * sigma


def estimate(left: npt.ArrayLike, right: npt.ArrayLike, max_disp: int = 256,
             corners: int = CORNERS, terms: tuple[str, ...] = FITTED) -> Misalignment:
    """
    Return the `Misalignment` of the rectified pair (left, right).

    Images as `StereoPipeline` takes them (gray or colour, any dtype and scale, one size);
    `max_disp` px, the largest disparity a match may have; `terms`, those of TERMS to fit
    (least squares over the robust fit's inliers, each with its standard error). About
    65 ms on a 1242x375 pair (2 CPU cores). Unknown, saying why: a dark or textureless pair,
    one saturated apart from the other (over half of it near its maximum), fewer than
    MIN_MATCHES matches kept or agreeing, their residual above MAX_RESIDUAL or the used
    field's largest standard error above MAX_ERROR.
    """
    lg, rg = gray_pair(left, right)
    shape = lg.shape
    if min(shape) < 2 * WINDOW:
        return unknown('small', f'{shape[1]}x{shape[0]} is too small to track {WINDOW} px '
                       'windows', shape)
    gloom = dark(lg) or dark(rg)
    pts = corners_of(lg, corners)
    if len(pts) < MIN_MATCHES:
        return unknown('dark' if gloom else 'textureless',
                       f'{"dark" if gloom else "textureless"}: {len(pts)} corners, fewer '
                       f'than {MIN_MATCHES}', shape)
    cl, cr = clipped(lg, rg)
    p, q = track(standardized(lg), standardized(rg), pts, max_disp, cl, cr)
    if len(p) < MIN_MATCHES:
        glare = max(cl.mean(), cr.mean())
        cause = 'dark' if gloom else 'saturated' if glare > 0.5 else 'few matches'
        why = f'{cause}: ' if cause != 'few matches' else ''
        return unknown(cause, f'{why}{len(p)} matches, fewer than {MIN_MATCHES}', shape,
                       len(p))
    used = [TERMS.index(t) for t in TERMS if t in terms]
    x = basis(q[:, 0], q[:, 1], shape)[:, used]
    v = (q[:, 1] - p[:, 1]).astype(float)
    _, inl = robust_fit(x, v)
    n = int(inl.sum())
    if n < MIN_MATCHES:
        return unknown('few matches', f'{n} of {len(p)} matches agree, fewer than '
                       f'{MIN_MATCHES}', shape, n)
    xi, vi = x[inl], v[inl]
    coef = np.linalg.lstsq(xi, vi, rcond=None)[0]
    res = vi - xi @ coef
    residual = float(np.sqrt(res @ res / max(n - len(used), 1)))
    cov = residual ** 2 * np.linalg.pinv(xi.T @ xi)
    fitted, errors = np.zeros(len(TERMS)), np.zeros(len(TERMS))
    fitted[used], errors[used] = coef, np.sqrt(np.maximum(np.diag(cov), 0))
    keep = np.abs(coef) >= SIGNIFICANCE * errors[used]
    g = basis(*grid(shape), shape).reshape(-1, len(TERMS))[:, used] * keep
    error = float(np.sqrt(np.einsum('ij,jk,ik->i', g, cov, g).max()))
    if residual > MAX_RESIDUAL:
        return unknown('disagree', f'matches disagree: residual {residual:.2f} px > '
                       f'{MAX_RESIDUAL}', shape, n, residual, error)
    if error > MAX_ERROR:
        return unknown('uncertain', f'uncertain: error {error:.2f} px > {MAX_ERROR}', shape,
                       n, residual, error)
    return Misalignment(True, tuple(map(float, fitted)), tuple(map(float, errors)),
                        (int(shape[0]), int(shape[1])), n, residual, error)


def lanczos_table(a: int = 4, phases: int = 256) -> Image:
    """Return Lanczos-`a` weights (phases + 1, 2 a): row p for the fraction p / phases."""
    t = np.arange(1 - a, a + 1)[None, :] - np.linspace(0, 1, phases + 1)[:, None]
    w = np.sinc(t) * np.sinc(t / a)
    return (w / w.sum(1, keepdims=True)).astype(np.float32)


LANCZOS = lanczos_table()


@njit(inline='always')
def _phase(pos: float, phases: int) -> tuple[int, int]:
    """Return (floor of pos, the table row of its fraction)."""
    i = int(np.floor(pos))
    return i, int((pos - i) * phases + 0.5)


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def _resample(src: Image, coef: Image, slope: np.float32, table: Image) -> Image:
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


def _slope(m: Misalignment) -> float:
    """Return the roll as the slope (px per px) of the rotation it is."""
    return m.term('roll') / max((m.shape[1] - 1) / 2, 1.0)


def correct(right: npt.ArrayLike, misalignment: Misalignment,
            min_correction: float = MIN_CORRECTION,
            max_correction: float = MAX_CORRECTION) -> npt.ArrayLike:
    """
    Return the right image resampled to line up with the left one, or `right` itself.

    `right`: the image the estimate was made with (any input `estimate` takes). The right
    pixel that belongs at (x, y) is (x - roll (y - cy) / cx, y + v(x, y)): v undone, and
    the roll undone as the rotation it is (its horizontal part too), by Lanczos
    interpolation (8 taps each way, which blurs far less than bilinear or bicubic), edges
    replicated; float32 gray out. Unchanged (the same object) unless `verdict` says
    'corrected': unknown, or the largest abs(v) below `min_correction` or above
    `max_correction` px. About 5-10 ms at 1242x375.
    """
    m = misalignment
    if m.verdict(min_correction, max_correction) != 'corrected':
        return right
    gray = to_gray(right, 'right image')
    if gray.shape != tuple(m.shape):
        raise ValueError(f'the right image is {gray.shape[1]}x{gray.shape[0]} but the '
                         f'misalignment was estimated on {m.shape[1]}x{m.shape[0]}')
    return _resample(gray, np.asarray(m.coefficients, np.float32), np.float32(_slope(m)),
                     LANCZOS)


def fold(misalignment: Misalignment, map_x: Image, map_y: Image) -> tuple[Image, Image]:
    """
    Return rectification maps (float32 (H, W), as cv2.remap takes) that also correct.

    `map_x`, `map_y`: where each rectified right pixel is taken from in the raw image; the
    result takes it from where the corrected pixel's source (`correct`'s) lies, so that one
    cv2.remap rectifies and corrects the raw right image (bilinear between map values).
    """
    m = misalignment
    h, w = map_x.shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    xs = x - np.float32(_slope(m)) * (y - np.float32((h - 1) / 2))
    ys = y + m.at(x, y).astype(np.float32)
    mx, my = (cv2.remap(a, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
              for a in (map_x, map_y))
    return np.asarray(mx, np.float32), np.asarray(my, np.float32)
