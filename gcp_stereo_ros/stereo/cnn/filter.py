"""
The guided filter of the CNN confidence volume, before its best disparities are taken.

The CNN sees a 9x9 patch: alone, its best disparity is often more than 3 px off (doc/method.md,
"The guided filter of the CNN volume"). Filtering each disparity slice Vol(., ., d) with
a guided filter (He, Sun, Tang, PAMI 2013; on matching volumes, Rhemann et al., CVPR 2011),
the left image as the guide, pools the evidence of a (2r + 1)^2 window where the image is
smooth and stops at its edges. With the filtered volume Vol', cof_c = max_d Vol' and cof_d =
argmax_d Vol', as `cnn.confidence` takes them from Vol without it; the right view's cof_dr
stays that of Vol, argmax_d Vol(y, xr + d, d). So `gcp_lr_check` holds the filtered
disparity against the unfiltered right view: it rejects the GCPs whose disparity the filter
moved alike in both views, such as a foreground fattened over its background (what the
unfiltered right view gains over the filtered one: doc/method.md).
Per slice, with I the left image standardized (`images.standardize`,
what the CNN sees), p = Vol(., ., d) and mean() the mean over the window clipped to the image:

    a = (mean(I p) - mean(I) mean(p)) / (var(I) + GUIDE_EPS),  b = mean(p) - a mean(I)
    Vol' = mean(a) I + mean(b)

Cells with x - d < 0 have Vol = 0 (as in `cnn`) and take part in the means; they are never
a best disparity. A row of Vol' reads 2r rows of Vol above and below it (`halo`). On the
CPU `StripFilter` takes the CNN's descriptors strip by strip as `cnn.confidence` computes
them: it correlates each strip's rows once into a ring of raw rows (`cnn.correlation.
volume`, which also takes cof_dr), then filters them in one pass, block by block of columns,
each block sliding its column sums down the rows and holding its last rows of a and b, so
neither the coefficients nor Vol' are ever written out whole. `cuda.cnn.filtered_best` is
the torch twin. The float32 sums are slid (a row or column enters, one leaves) in a fixed
order, so the results do not depend on the number of threads; they equal the formula's
within float rounding (cof_c within 2e-5 of float64; cof_d differs only where two
disparities tie within that).
"""
from numba import njit, prange
import numpy as np
import numpy.typing as npt

from .correlation import first_argmax, volume

# Of the guide's variance (1: the image is standardized); the error rates of other values:
# doc/notes/implementation_history.md.
GUIDE_EPS = 0.01
# Rows of a band: `box_means` slides its sums down each band and restarts at the next (the
# threads share the bands), `StripFilter` recomputes its column sums every BAND_ROWS rows (a
# bound on the rounding the slides accumulate). Fixed, it keeps the results independent of
# the threads.
BAND_ROWS = 16
# Columns of a block of `StripFilter`'s pass (the threads share the blocks): the column sums
# of its 2r columns either side are made twice, by it and its neighbour. Fixed, as BAND_ROWS.
BLOCK_COLS = 128


def halo(radius: int) -> int:
    """Return the rows of the volume above and below a strip that its filter reads: 2 r."""
    return 2 * radius


@njit(inline='always', fastmath=True)
def _add_row(src1: np.ndarray, src2: np.ndarray, weight: np.ndarray, y: int, sign: np.float32,
             col1: np.ndarray, col2: np.ndarray) -> None:
    """col1 += sign src1[y]; col2 += sign weight[y] src2[y] (src (rows, W, k), col (W, k))."""
    for x in range(col1.shape[0]):
        g = sign * weight[y, x]
        for c in range(col1.shape[1]):
            col1[x, c] += sign * src1[y, x, c]
            col2[x, c] += g * src2[y, x, c]


@njit(inline='always', fastmath=True)
def _slide(n: int, radius: int, y: int, first_row: bool, src1: np.ndarray, src2: np.ndarray,
           weight: np.ndarray, col1: np.ndarray, col2: np.ndarray) -> int:
    """
    Make col1, col2 the column sums of src1, weight src2 over the rows |y' - y| <= radius.

    From those of row y - 1 (a row enters, one leaves), or from scratch at `first_row`;
    returns the number of rows summed (the window clipped to the n rows).
    """
    lo, hi = max(0, y - radius), min(n, y + radius + 1)
    if first_row:
        col1[:] = 0
        col2[:] = 0
        for yy in range(lo, hi):
            _add_row(src1, src2, weight, yy, np.float32(1.0), col1, col2)
    else:
        if y + radius < n:
            _add_row(src1, src2, weight, y + radius, np.float32(1.0), col1, col2)
        if y - radius - 1 >= 0:
            _add_row(src1, src2, weight, y - radius - 1, np.float32(-1.0), col1, col2)
    return hi - lo


@njit(inline='always', fastmath=True)
def _across(col: np.ndarray, x: int, radius: int, acc: np.ndarray) -> int:
    """Slide the row sum acc of col's columns |x' - x| <= radius from x - 1 to x."""
    w = col.shape[0]
    if x == 0:
        acc[:] = 0
        for xx in range(min(radius, w)):
            for c in range(col.shape[1]):
                acc[c] += col[xx, c]
    if x + radius < w:
        for c in range(col.shape[1]):
            acc[c] += col[x + radius, c]
    if x - radius - 1 >= 0:
        for c in range(col.shape[1]):
            acc[c] -= col[x - radius - 1, c]
    return min(w, x + radius + 1) - max(0, x - radius)


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def box_means(src: np.ndarray, weight: np.ndarray, radius: int, means: np.ndarray,
              weighted: np.ndarray, blocks: int) -> None:
    """
    Write the window means of src (rows, W, k) and of weight (rows, W) src into the two outs.

    Each window is (2 radius + 1)^2 px clipped to src's rows and columns; the rows go in
    `blocks` bands, each band's column sums slid down it.
    """
    n, w, k = src.shape
    for band in prange(blocks):
        col1, col2 = np.empty((w, k), np.float32), np.empty((w, k), np.float32)
        acc1, acc2 = np.empty(k, np.float32), np.empty(k, np.float32)
        for y in range(band * n // blocks, (band + 1) * n // blocks):
            rows = _slide(n, radius, y, y == band * n // blocks, src, src, weight, col1, col2)
            for x in range(w):
                _across(col2, x, radius, acc2)
                inv = np.float32(1.0) / np.float32(rows * _across(col1, x, radius, acc1))
                for c in range(k):
                    means[y, x, c] = acc1[c] * inv
                    weighted[y, x, c] = acc2[c] * inv


def guide_stats(guide: np.ndarray, radius: int
                ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """Return the window means of I and its variance, float32 (H, W) each, of I (float32)."""
    mean, square = (np.empty(guide.shape + (1,), np.float32) for _ in range(2))
    box_means(guide[..., None], guide, radius, mean, square, _blocks(guide.shape[0]))
    mean = mean[..., 0]
    return mean, np.maximum(square[..., 0] - mean * mean, 0)


def _blocks(rows: int) -> int:
    """
    Return the bands of `rows` rows `box_means` slides its sums down, BAND_ROWS each.

    The threads share the bands; the sums restart at each band, so a fixed band height makes
    the float32 results the same whatever the number of threads (a machine with more cores,
    a worker with one).
    """
    return max(1, -(-rows // BAND_ROWS))


@njit(inline='always', fastmath=True)
def _enter(ring: np.ndarray, q1: int, q2: int, col: int, sums: np.ndarray, s: int, lx: int, y: int,
           radius: int, guide: np.ndarray | None, x: int) -> None:
    """
    Slide the column sums sums[s], sums[s + 1] at block column lx down to row y.

    They sum the rows y - 2r .. y (clipped) of ring[q1] and ring[q2] at column `col` (row
    y' in slot y' % their rows), ring[q2]'s times guide[y', x] unless `guide` is None: those
    of y - 1 with row y added and y - 2r - 1 removed, recomputed every BAND_ROWS-th row.
    """
    n, nd = ring.shape[1], ring.shape[3]
    new = y % n
    g = guide[y, x] if guide is not None else np.float32(1.0)
    if y % BAND_ROWS == 0:
        for d in range(nd):
            sums[s, lx, d] = 0
            sums[s + 1, lx, d] = 0
        for yy in range(max(0, y - 2 * radius), y + 1):
            gy = guide[yy, x] if guide is not None else np.float32(1.0)
            for d in range(nd):
                sums[s, lx, d] += ring[q1, yy % n, col, d]
                sums[s + 1, lx, d] += gy * ring[q2, yy % n, col, d]
    elif y > 2 * radius:
        old = (y - 2 * radius - 1) % n
        go = guide[y - 2 * radius - 1, x] if guide is not None else np.float32(1.0)
        for d in range(nd):
            sums[s, lx, d] += ring[q1, new, col, d] - ring[q1, old, col, d]
            sums[s + 1, lx, d] += g * ring[q2, new, col, d] - go * ring[q2, old, col, d]
    else:
        for d in range(nd):
            sums[s, lx, d] += ring[q1, new, col, d]
            sums[s + 1, lx, d] += g * ring[q2, new, col, d]


@njit(inline='always', fastmath=True)
def _leave(ring: np.ndarray, q1: int, q2: int, col: int, sums: np.ndarray, s: int, lx: int, y: int,
           guide: np.ndarray | None, x: int) -> None:
    """Remove row y of ring[q1], ring[q2] (as `_enter` adds it) from sums[s], sums[s + 1]."""
    slot = y % ring.shape[1]
    g = guide[y, x] if guide is not None else np.float32(1.0)
    for d in range(ring.shape[3]):
        sums[s, lx, d] -= ring[q1, slot, col, d]
        sums[s + 1, lx, d] -= g * ring[q2, slot, col, d]


@njit(inline='always', fastmath=True)
def _row_sums(sums: np.ndarray, s: int, x: int, off: int, w: int, radius: int, first: bool,
              acc: np.ndarray) -> tuple[int, np.float32, int, np.float32, int]:
    """
    Return how to slide acc[0], acc[1] from the window of x - 1 to that of x.

    They sum sums[s], sums[s + 1] over the columns |x' - x| <= r clipped to the image's w
    (block column = image column - off). The caller adds column `cin` times `enter` and
    subtracts `cout` times `leave`; where `first` they are summed from scratch here and both
    weights are 0. Returns (cin, enter, cout, leave, the number of columns in the window).
    """
    lo, hi = max(0, x - radius), min(w - 1, x + radius)
    zero, one = np.float32(0.0), np.float32(1.0)
    if not first:
        return (hi - off, one if x + radius < w else zero, max(0, x - radius - 1) - off,
                one if x - radius - 1 >= 0 else zero, hi - lo + 1)
    for d in range(sums.shape[2]):
        acc[0, d] = 0
        acc[1, d] = 0
    for xx in range(lo - off, hi + 1 - off):
        for d in range(sums.shape[2]):
            acc[0, d] += sums[s, xx, d]
            acc[1, d] += sums[s + 1, xx, d]
    return lo - off, zero, lo - off, zero, hi - lo + 1


@njit(inline='always', fastmath=True)
def _coefficient_row(y: int, lo: int, hi: int, off: int, h: int, w: int, guide: np.ndarray,
                     mean_i: np.ndarray, var_i: np.ndarray, radius: int, held: np.ndarray,
                     sums: np.ndarray, acc: np.ndarray) -> None:
    """
    Hold a and b (the module's formula) of row y, columns lo..hi, and slide their sums.

    As `_enter` slides them, in the same loop where no restart is due.
    """
    rows = min(h - 1, y + radius) - max(0, y - radius) + 1
    slot, old = y % held.shape[1], (y - 2 * radius - 1) % held.shape[1]
    fused = y % BAND_ROWS != 0 and y > 2 * radius
    for x in range(lo, hi):
        lx = x - off
        cin, enter, cout, leave, cols = _row_sums(sums, 0, x, off, w, radius, x == lo, acc)
        inv_n = np.float32(1.0) / np.float32(rows * cols)
        mi = mean_i[y, x]
        inv = np.float32(1.0) / (var_i[y, x] + np.float32(GUIDE_EPS))
        for d in range(held.shape[3]):
            p = acc[0, d] + (enter * sums[0, cin, d] - leave * sums[0, cout, d])
            ip = acc[1, d] + (enter * sums[1, cin, d] - leave * sums[1, cout, d])
            acc[0, d] = p
            acc[1, d] = ip
            mp = p * inv_n
            a = (ip * inv_n - mi * mp) * inv
            held[0, slot, lx, d] = a
            held[1, slot, lx, d] = mp - a * mi
        if fused:
            for d in range(held.shape[3]):
                sums[2, lx, d] += held[0, slot, lx, d] - held[0, old, lx, d]
                sums[3, lx, d] += held[1, slot, lx, d] - held[1, old, lx, d]
        else:
            _enter(held, 0, 1, lx, sums, 2, lx, y, radius, None, x)


@njit(inline='always', fastmath=True)
def _output_row(y: int, x0: int, x1: int, off: int, h: int, w: int, guide: np.ndarray, radius: int,
                sums: np.ndarray, acc: np.ndarray, keys: np.ndarray, cof_c: np.ndarray,
                cof_d: np.ndarray) -> None:
    """
    Write max / first argmax over d <= x of Vol' of row y, columns x0..x1.

    Vol' is written into acc[2] (`keys`: acc viewed as int32).
    """
    rows = min(h - 1, y + radius) - max(0, y - radius) + 1
    for x in range(x0, x1):
        cin, enter, cout, leave, cols = _row_sums(sums, 2, x, off, w, radius, x == x0, acc)
        inv_n = np.float32(1.0) / np.float32(rows * cols)
        g = guide[y, x] * inv_n
        for d in range(sums.shape[2]):
            mean_a = acc[0, d] + (enter * sums[2, cin, d] - leave * sums[2, cout, d])
            mean_b = acc[1, d] + (enter * sums[3, cin, d] - leave * sums[3, cout, d])
            acc[0, d] = mean_a
            acc[1, d] = mean_b
            acc[2, d] = mean_a * g + mean_b * inv_n
        arg = first_argmax(keys, 2, min(sums.shape[2], x + 1))
        cof_c[y, x] = acc[2, arg]
        cof_d[y, x] = arg


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def _filter_rows(raw: np.ndarray, y0: int, y1: int, guide: np.ndarray, mean_i: np.ndarray,
                 var_i: np.ndarray, radius: int, held: np.ndarray, sums: np.ndarray,
                 acc: np.ndarray, cof_c: np.ndarray, cof_d: np.ndarray) -> None:
    """
    Filter the raw rows y0..y1 (row y in raw[y % its rows]), block by block of columns.

    Each block holds its last 2r + 2 rows of the coefficients and the column sums of both
    (`held`, `sums`) from one call to the next: the output rows lag the raw ones by 2r, all
    written when y1 is the image's last row.
    """
    (h, w), nb = guide.shape, held.shape[0]
    for blk in prange(nb):
        x0 = blk * BLOCK_COLS
        x1 = min(w, x0 + BLOCK_COLS)
        off = x0 - 2 * radius  # block column of image column x: x - off
        lo, hi = max(0, off), min(w, x1 + 2 * radius)  # the raw volume's columns
        lo_c, hi_c = max(0, x0 - radius), min(w, x1 + radius)  # the coefficients'
        held_b, sums_b, acc_b = held[blk], sums[blk], acc[blk]
        keys, ring = acc_b.view(np.int32), raw.reshape((1,) + raw.shape)
        for y in range(y0, y1):
            for x in range(lo, hi):
                _enter(ring, 0, 0, x, sums_b, 0, x - off, y, radius, guide, x)
            if y >= radius:
                _coefficient_row(y - radius, lo_c, hi_c, off, h, w, guide, mean_i, var_i,
                                 radius, held_b, sums_b, acc_b)
            if y >= 2 * radius:
                _output_row(y - 2 * radius, x0, x1, off, h, w, guide, radius, sums_b, acc_b,
                            keys, cof_c, cof_d)
        if y1 < h:
            continue
        for y in range(max(0, h - radius), h):  # the rows below the image are none
            for x in range(lo, hi):
                if y - radius - 1 >= 0:
                    _leave(ring, 0, 0, x, sums_b, 0, x - off, y - radius - 1, guide, x)
            _coefficient_row(y, lo_c, hi_c, off, h, w, guide, mean_i, var_i, radius, held_b,
                             sums_b, acc_b)
            if y >= radius:
                _output_row(y - radius, x0, x1, off, h, w, guide, radius, sums_b, acc_b,
                            keys, cof_c, cof_d)
        for y in range(max(0, h - radius), h):
            for x in range(lo_c, hi_c):
                if y - radius - 1 >= 0:
                    _leave(held_b, 0, 1, x - off, sums_b, 2, x - off, y - radius - 1, None, x)
            _output_row(y, x0, x1, off, h, w, guide, radius, sums_b, acc_b, keys, cof_c,
                        cof_d)


def _layout(width: int, max_disp: int, radius: int, strip_rows: int
            ) -> tuple[tuple[int, ...], ...]:
    """Return the shapes of a `StripFilter`'s accumulators, raw rows, coefficients and sums."""
    blocks, span = -(-width // BLOCK_COLS), BLOCK_COLS + 4 * radius
    padded = -(-max_disp // 16) * 16  # each accumulator on a 64-byte line
    return ((blocks, 3, padded), (strip_rows + 2 * radius + 1, width, max_disp),
            (blocks, 2, 2 * radius + 2, span, max_disp), (blocks, 4, span, max_disp))


def scratch_size(height: int, width: int, max_disp: int, radius: int, strip_rows: int) -> int:
    """
    Return the float32 values a `StripFilter` holds.

    The raw volume of a strip of min(height, strip_rows) rows and of the 2r + 1 rows before
    it; per block of columns, the last 2r + 2 rows of the two coefficients and the column
    sums of both.
    """
    shapes = _layout(width, max_disp, radius, min(height, strip_rows))
    return sum(int(np.prod(s)) for s in shapes) + 16


class StripFilter:
    """
    Correlates and filters the CNN descriptors of an image as its strips of rows come.

    `add` takes each strip's raw descriptors (`cnn.correlation`'s bits), writes its rows of
    cof_dr and the outputs of every row whose rows below have come (all rows at the last
    strip) into cof_c (raw), cof_d, (H, W) each. `scratch`: a float32 array of at least
    `scratch_size` values for what it holds between strips (allocated if None; a caller
    that keeps one between images spares the page faults of fresh memory).
    """

    def __init__(self, guide: np.ndarray, radius: int, max_disp: int, strip_rows: int,
                 cof_c: np.ndarray, cof_d: np.ndarray, cof_dr: np.ndarray,
                 scratch: np.ndarray | None = None) -> None:
        h, w = guide.shape
        self.guide = np.ascontiguousarray(guide, np.float32)
        self.radius, self.outputs = radius, (cof_c, cof_d, cof_dr)
        self.stats = guide_stats(self.guide, radius)
        size = scratch_size(h, w, max_disp, radius, strip_rows)
        scratch = np.empty(size, np.float32) if scratch is None else scratch[:size]
        start = -scratch.ctypes.data % 64 // 4  # the accumulators' lines aligned
        self.arrays = []
        for shape in _layout(w, max_disp, radius, min(h, strip_rows)):
            n = int(np.prod(shape))
            self.arrays.append(scratch[start:start + n].reshape(shape))
            start += n

    def add(self, bits: np.ndarray, shift: int, y0: int) -> None:
        """Correlate and filter rows y0.. (at most strip_rows), whose descriptors `bits` holds."""
        acc, raw, held, sums = self.arrays
        cof_c, cof_d, cof_dr = self.outputs
        y1 = y0 + bits.shape[1]
        if y1 - y0 > raw.shape[0] - 2 * self.radius - 1:
            raise ValueError(f'a strip of {y1 - y0} rows, more than the {raw.shape[0]} held rows '
                             f'less 2r + 1')
        volume(bits, shift, raw, y0 % raw.shape[0], cof_dr[y0:y1])  # row y in raw[y % rows]
        _filter_rows(raw, y0, y1, self.guide, *self.stats, self.radius, held, sums, acc, cof_c,
                     cof_d)
