"""
The guided filter of the CNN confidence volume, before its best disparities are taken.

The CNN sees a 9x9 patch: alone, its best disparity is wrong by more than 3 px on about a
sixth of the KITTI pixels (doc/method.md). Filtering each disparity slice Vol(., ., d) with
a guided filter (He, Sun, Tang, PAMI 2013; on matching volumes, Rhemann et al., CVPR 2011),
the left image as the guide, pools the evidence of a (2r + 1)^2 window where the image is
smooth and stops at its edges. With the filtered volume Vol', cof_c = max_d Vol' and cof_d =
argmax_d Vol', as `cnn.confidence` takes them from Vol without it; the right view's cof_dr
stays that of Vol, argmax_d Vol(y, xr + d, d). So `gcp_lr_check` holds the filtered
disparity against the unfiltered right view: it rejects the GCPs whose disparity the filter
moved alike in both views, such as a foreground fattened over its background (on the 10
KITTI 2015 validation frames, with the filtered right view instead, 1.47 % of the pixels
were published more than 3 px too near, with this one 1.29 %, as unfiltered; doc/method.md).
Per slice, with I the left image standardized (`images.standardize`,
what the CNN sees), p = Vol(., ., d) and mean() the mean over the window clipped to the image:

    a = (mean(I p) - mean(I) mean(p)) / (var(I) + GUIDE_EPS),  b = mean(p) - a mean(I)
    Vol' = mean(a) I + mean(b)

Cells with x - d < 0 have Vol = 0 (as in `cnn`) and take part in the means; they are never
a best disparity. A row of Vol' reads 2r rows of Vol above and below it (`halo`). On the
CPU `StripFilter` takes the raw volume strip by strip as `cnn.confidence` computes it and
keeps the 4r rows the next strip's outputs read, so each raw row is computed once
(`filtered_best`; 2r rows of coefficients at each strip's edge twice); `cnn_cuda.
filtered_best` is the torch twin. The kernels are compiled with fastmath, which assumes no
infinities: every maximum starts from a real value.
"""
from numba import njit, prange
import numpy as np

# Of the guide's variance (1: the image is standardized). On the 14 validation frames a first
# implementation (windows replicating the image's edge) gave Census+GCP 4.77, 4.76, 4.77 %
# with 0.001, 0.01, 0.03 (radius 4, P2 128, every pixel published, integer disparities).
GUIDE_EPS = 0.01
# Rows of a band: the kernels' sums slide down each band and restart at the next (the
# threads share the bands). A fixed height keeps the results independent of the threads.
BAND_ROWS = 16


def halo(radius):
    """Return the rows of the volume above and below a strip that its filter reads: 2 r."""
    return 2 * radius


@njit(inline='always', fastmath=True)
def _add_row(src1, src2, weight, y, sign, col1, col2):
    """col1 += sign src1[y]; col2 += sign weight[y] src2[y] (src (rows, W, k), col (W, k))."""
    for x in range(col1.shape[0]):
        g = sign * weight[y, x]
        for c in range(col1.shape[1]):
            col1[x, c] += sign * src1[y, x, c]
            col2[x, c] += g * src2[y, x, c]


@njit(inline='always', fastmath=True)
def _slide(n, radius, y, first_row, src1, src2, weight, col1, col2):
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
def _across(col, x, radius, acc):
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
def box_means(src, weight, radius, means, weighted, blocks):
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


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def _coefficients(vol, guide, mean_i, var_i, radius, first, a, b, blocks):
    """Write a and b (the module's formula) of the rows first.. of vol into a and b."""
    n, w, nd = vol.shape
    rows = a.shape[0]
    for band in prange(blocks):
        col_p, col_ip = np.empty((w, nd), np.float32), np.empty((w, nd), np.float32)
        acc_p, acc_ip = np.empty(nd, np.float32), np.empty(nd, np.float32)
        for i in range(band * rows // blocks, (band + 1) * rows // blocks):
            y = first + i
            count = _slide(n, radius, y, i == band * rows // blocks, vol, vol, guide, col_p,
                           col_ip)
            for x in range(w):
                _across(col_ip, x, radius, acc_ip)
                inv_n = np.float32(1.0) / np.float32(count * _across(col_p, x, radius, acc_p))
                mi = mean_i[y, x]
                inv = np.float32(1.0) / (var_i[y, x] + np.float32(GUIDE_EPS))
                for d in range(nd):
                    mp = acc_p[d] * inv_n
                    ai = (acc_ip[d] * inv_n - mi * mp) * inv
                    a[i, x, d] = ai
                    b[i, x, d] = mp - ai * mi


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def _best(a, b, raw, guide, radius, first, cof_c, cof_d, cof_dr, blocks):
    """
    Write max / first argmax over d of Vol' of the rows first.. of a and b (and guide).

    And the right view's argmax over d of the raw volume, whose rows `raw` are the outputs'.
    """
    n, w, nd = a.shape
    rows = cof_c.shape[0]
    ones = np.ones((n, w), np.float32)
    for band in prange(blocks):
        col_a, col_b = np.empty((w, nd), np.float32), np.empty((w, nd), np.float32)
        acc_a, acc_b = np.empty(nd, np.float32), np.empty(nd, np.float32)
        right_best = np.empty(w, np.float32)
        right_arg = np.empty(w, np.int32)
        for i in range(band * rows // blocks, (band + 1) * rows // blocks):
            y = first + i
            count = _slide(n, radius, y, i == band * rows // blocks, a, b, ones, col_a, col_b)
            right_best[:] = -1.0  # below every raw cosine
            right_arg[:] = 0
            for x in range(w):
                _across(col_b, x, radius, acc_b)
                inv_n = np.float32(1.0) / np.float32(count * _across(col_a, x, radius, acc_a))
                g = guide[y, x] * inv_n
                best = acc_a[0] * g + acc_b[0] * inv_n
                arg = 0
                for d in range(min(nd, x + 1)):
                    v = acc_a[d] * g + acc_b[d] * inv_n
                    if v > best:
                        best = v
                        arg = d
                    r = raw[i, x, d]
                    if r > right_best[x - d]:  # x, so d, grows for a fixed x - d: first max
                        right_best[x - d] = r
                        right_arg[x - d] = d
                cof_c[i, x] = best
                cof_d[i, x] = arg
            for x in range(w):
                cof_dr[i, x] = right_arg[x]


def guide_stats(guide, radius):
    """Return the window means of I and its variance, float32 (H, W) each, of I (float32)."""
    mean, square = (np.empty(guide.shape + (1,), np.float32) for _ in range(2))
    box_means(guide[..., None], guide, radius, mean, square, _blocks(guide.shape[0]))
    mean = mean[..., 0]
    return mean, np.maximum(square[..., 0] - mean * mean, 0)


def filtered_best(vol, guide, stats, radius, first, cof_c, cof_d, cof_dr, work):
    """
    Write cof_c (not calibrated), cof_d, cof_dr of a strip from its raw volume, on the CPU.

    `vol`: float32 (rows, W, D), the raw volume of the strip's rows and of up to `halo`
    rows above and below it (fewer at the image's edges); `guide` and `stats` (mean_i,
    var_i: `guide_stats` of the whole image) for the same rows; `first`: the strip's first
    row in vol; the outputs are (strip rows, W). `work`: a float32 array of at least
    2 (vol rows) W D values to hold the filter's coefficients.
    """
    lo = max(0, first - radius)
    hi = min(vol.shape[0], first + cof_c.shape[0] + radius)
    size = (hi - lo) * vol.shape[1] * vol.shape[2]
    a, b = (work[k * size:(k + 1) * size].reshape((hi - lo,) + vol.shape[1:]) for k in (0, 1))
    _coefficients(vol, guide, *stats, radius, lo, a, b, _blocks(hi - lo))
    _best(a, b, vol[first:first + cof_c.shape[0]], guide[lo:hi], radius, first - lo, cof_c,
          cof_d, cof_dr, _blocks(cof_c.shape[0]))


def scratch_size(height, width, max_disp, radius, strip_rows):
    """Return the float32 values a `StripFilter` holds: three arrays of its rows of the volume."""
    return 3 * min(height, strip_rows + 2 * halo(radius)) * width * max_disp


def _blocks(rows):
    """
    Return the bands of `rows` rows the kernels slide their sums down, BAND_ROWS each.

    The threads share the bands; the sums restart at each band, so a fixed band height makes
    the float32 results the same whatever the number of threads (a machine with more cores,
    a worker with one).
    """
    return max(1, -(-rows // BAND_ROWS))


class StripFilter:
    """
    Filters the raw volume of an image as its strips of rows come, on the CPU.

    For each strip, `rows` gives the array to write its raw volume rows into; `filter_held`
    then writes the outputs of every row whose halo below has come (all rows after the
    last strip) into cof_c (raw), cof_d and cof_dr, (H, W) each. The volume of a strip and
    the 4r rows before it are held, so each raw row is computed once. `scratch`: a float32
    array of at least `scratch_size` values to hold them and the filter's coefficients
    (allocated if None; a caller that keeps one between images spares the page faults of
    fresh memory).
    """

    def __init__(self, guide, radius, max_disp, strip_rows, cof_c, cof_d, cof_dr,
                 scratch=None):
        h, w = guide.shape
        self.guide = np.ascontiguousarray(guide, np.float32)  # for every strip's kernels
        self.radius, self.outputs = radius, (cof_c, cof_d, cof_dr)
        self.stats = guide_stats(self.guide, radius)
        self.carry = 2 * halo(radius)  # the rows the next strip's first output reads above
        size = scratch_size(h, w, max_disp, radius, strip_rows)
        scratch = np.empty(size, np.float32) if scratch is None else scratch
        self.buffer = scratch[:size // 3].reshape(-1, w, max_disp)
        self.work = scratch[size // 3:size]
        self.top = self.end = self.done = 0  # image rows: buffer[0], after the last, output

    def rows(self, y0, y1):
        """Return the (y1 - y0, W, D) array for the raw rows y0..y1 (y0: the last strip's end)."""
        if self.end - self.top > self.carry:  # (numpy copies overlapping rows right)
            self.buffer[:self.carry] = self.buffer[self.end - self.top - self.carry:
                                                   self.end - self.top]
            self.top = self.end - self.carry
        self.end = y1
        return self.buffer[y0 - self.top:y1 - self.top]

    def filter_held(self):
        """Write the outputs of the rows whose volume below is held."""
        h = self.guide.shape[0]
        stop = h if self.end == h else self.end - halo(self.radius)
        if stop <= self.done:
            return
        held = slice(self.top, self.end)
        filtered_best(self.buffer[:self.end - self.top], self.guide[held],
                      [s[held] for s in self.stats], self.radius, self.done - self.top,
                      *(a[self.done:stop] for a in self.outputs), self.work)
        self.done = stop
