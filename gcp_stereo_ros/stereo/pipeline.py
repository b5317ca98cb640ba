"""
The one stereo pipeline every caller uses: evaluation, the ROS node and the bag tools.

`StereoPipeline` runs the stages of a `stages.Backend` once, in order, over explicit
buffers: upload -> CNN confidence -> cost volume -> plain SGM -> GCP selection and
refinement -> SGM -> winner-takes-all (and median) -> disparity confidence ->
invalidation (`postprocess`) -> one download of what is published. Its settings are a
`config.StereoConfig`, its memory is bounded by `memory.memory_bytes`.
"""
from dataclasses import dataclass
import time
from typing import Any, cast

import numpy as np

from .backend import backend
from .cancel import CancelFlag
from .cnn.filter import scratch_size
from .cnn.weights import confidence_fit
from .config import StereoConfig
from .images import bin_area, gray_pair, subsample, upsample
from .memory import call_glibc, check_memory, volume_arithmetic
from .stages import Backend, CnnConfidence

# The paths of plain SGM for `plain_check` and `gcp_plain_check`: horizontal and vertical
# (chosen on the validation frames: doc/published.md, "Plain SGM as a second opinion").
PLAIN_PATHS = 4


def filter_size(shape: tuple[int, int], max_disp: int, radius: int) -> int:
    """Return the float32 values the CPU's CNN filter holds for a pair of `shape` (0 without)."""
    if not radius:
        return 0
    from .cnn.network import STRIP_ROWS  # torch is imported only when GCPs are used
    return scratch_size(*shape, max_disp, radius, STRIP_ROWS)


@dataclass
class StereoResult:
    """
    What `StereoPipeline` returns for one pair: the disparity and what it was made from.

    Every array is (H, W), the size of the input images (with ``downsample`` > 1 blown
    back up to it), row y, column x of the left image. Disparities are in pixels of the
    input images: the left pixel (x, y) matches the right pixel (x - d, y).

    Attributes
    ----------
    disparity : numpy.ndarray
        float32 (H, W), px in [0, max_disp - 1], sub-pixel with ``subpixel``; NaN (never 0)
        where the invalidation (`postprocess.invalidate`) rejected the winner.
    gcp : numpy.ndarray or None
        bool (H, W): the ground control points; None without ``use_gcp``.
    cof_c : numpy.ndarray or None
        float32 (H, W) in [0, 1]: the CNN confidence, P(cof_d within 1 px of the truth),
        which theta cuts; None without ``use_gcp``.
    cof_d : numpy.ndarray or None
        int32 (H, W), px: the CNN's best disparity; None without ``use_gcp``.
    cof_dr : numpy.ndarray or None
        int32 (H, W), px: the right view's CNN disparity at each right pixel; None without
        ``use_gcp``.
    seconds : dict
        Wall time in seconds per stage that ran, in order: 'downsample', 'upload' (GPU),
        'cnn' and 'confidence' (the CNN and its correlation), 'cost', 'plain_sgm',
        'refine', 'sgm', 'wta', 'disparity_confidence', 'invalidate', 'download' (GPU),
        'upsample'.
    disparity_confidence : numpy.ndarray or None
        float32 (H, W) in [0, 1]: P(the published disparity within 3 px of the truth), 0
        where the disparity is NaN; None where no fit ships for the method and weights.
    consistent : numpy.ndarray
        bool (H, W): the right view's winner at x - d is within 1 px of d (x - d >= 0),
        whether or not ``lr_check`` invalidates by it.
    margin : numpy.ndarray
        float32 (H, W) in [0, 1]: the SGM cost margin 1 - S(winner) / S(rival).

    """

    disparity: np.ndarray
    gcp: np.ndarray | None
    cof_c: np.ndarray | None
    cof_d: np.ndarray | None
    cof_dr: np.ndarray | None
    seconds: dict[str, float]
    disparity_confidence: np.ndarray | None = None
    consistent: np.ndarray | None = None
    margin: np.ndarray | None = None

    @property
    def cnn(self) -> CnnConfidence | None:
        """Return the CNN's outputs, to pass as `StereoPipeline.__call__`'s `cnn`."""
        return None if self.cof_c is None else CnnConfidence(self.cof_c, self.cof_d, self.cof_dr)


class StereoPipeline:
    """
    Runs a StereoConfig on image pairs; the CNN is loaded once, on first use.

    The cost volume and the summed path costs are written into buffers the backend keeps
    from the previous pair of the same size and type (fresh ones would cost a page fault
    per 4 KiB); `release` lets them go. So one pipeline serves one thread at a time.
    """

    def __init__(self, config: StereoConfig | None = None, net: Any = None,
                 _backend: Backend | None = None) -> None:
        """
        Make a pipeline for `config` (default `StereoConfig()`); `net`: a loaded CNN.

        ValueError if the config's device cannot be used, or its confidence fit not read.
        """
        self.config = config or StereoConfig()  # checked when it was made
        self.backend = _backend or backend(self.config.device)
        self._net = net
        self.fit = confidence_fit(self.config)  # None if none ships

    def with_config(self, config: StereoConfig) -> 'StereoPipeline':
        """
        Return a pipeline for `config` that keeps this one's buffers and, if it can, its CNN.

        The CNN is kept when weights and device match, the buffers when the device does (the
        two pipelines must then not run at the same time).
        """
        device = config.device == self.config.device
        same = device and config.weights == self.config.weights
        return StereoPipeline(config, self._net if same else None,
                              self.backend if device else None)

    def release(self) -> None:
        """Let go of the kept buffers (of every pipeline sharing them), e.g. when idle."""
        self.backend.release()

    @property
    def net(self) -> Any:
        """
        Return the CNN, loaded on first use, on the config's device.

        ValueError if its weights have no calibration for the config's matched_radius, or
        precision 'int8' cannot run (`cnn.int8.branch`).
        """
        from .cnn.network import calibration, load_net  # torch is imported only when GCPs are used
        from .cnn.int8 import branch
        if self._net is None:
            self._net = load_net(self.config.weights or None, self.backend.torch_device)
        calibration(self._net, self.config.matched_radius)
        if self.config.precision == 'int8':
            branch(self._net)
        return self._net

    def __call__(self, left: np.ndarray, right: np.ndarray, cnn: CnnConfidence | None = None,
                 cancel: CancelFlag | None = None,
                 camera: tuple[float, float] | None = None,
                 timed: bool = False) -> StereoResult:
        """
        Return the `StereoResult` of one rectified pair.

        Parameters
        ----------
        left, right : numpy.ndarray
            The rectified images, of one size (H, W): gray (H, W) or (H, W, 1), RGB
            (H, W, 3) or RGBA (alpha ignored), RGB order; integer or float of any scale,
            finite. Colour becomes gray (BT.601 luma); the two may differ in dtype and
            channels. W must be at least max_disp / downsample.
        cnn : CnnConfidence, optional
            The CNN's outputs of an earlier run on the same pair, max_disp and downsample
            (`StereoResult.cnn`), to sweep GCP or SGM settings without the CNN (ignored
            without ``use_gcp``).
        cancel : CancelFlag, optional
            Another thread may set it to stop the run: raises ``cancel.Cancelled`` within
            a row of a CPU kernel or a CNN layer.
        camera : tuple of float, optional
            (f * T in px m, cx_left - cx_right in px): depth Z = f * T / (d - offset), for
            min_depth and max_depth; None: those limits are not applied.
        timed : bool
            Wait for the device at each stage's end, so that `StereoResult.seconds` holds
            each stage's device time (the bench); else a GPU's stages overlap the host and
            only their sum is the pair's time. The CPU's stages are timed either way.

        Returns
        -------
        StereoResult
            The disparity in px of the input images (NaN where invalid) and the maps it
            was made from, each (H, W), with each stage's wall time.

        Raises
        ------
        ValueError
            For images it cannot take (shape, dtype, NaN, unequal sizes, narrower than the
            disparity range, naming which), a `cnn` that is not three arrays, or a pair
            that would need more than memory_limit_mb, saying what to lower.

        """
        cfg, b = self.config, self.backend
        if cfg.use_gcp and cnn is not None:
            if len(cnn) != 3:
                raise ValueError('cnn must be (cof_c, cof_d, cof_dr), as StereoResult.cnn '
                                 'holds them')
            cnn = CnnConfidence(*cnn)
        seconds: dict[str, float] = {}
        t = time.perf_counter()

        def lap(stage: str | None) -> None:
            """Record the time since the last lap as `stage` (None: only restart the clock)."""
            nonlocal t
            if timed:
                b.synchronize()
            now = time.perf_counter()
            if stage is not None:
                seconds[stage] = now - t
            t = now
            if cancel is not None:
                cancel.check()

        left, right = gray_pair(left, right)
        check_memory(cfg, *left.shape)
        shape, f = left.shape, cfg.downsample
        if f > 1:
            left, right = bin_area(left, f), bin_area(right, f)
            if cfg.use_gcp and cnn is not None:  # undo the upsampling of its run
                cof_c, cof_d, cof_dr = (subsample(a, f, left.shape) for a in cnn)
                cnn = CnnConfidence(cof_c, cof_d // f, cof_dr // f)
            lap('downsample')
        nd = cfg.matched_disp
        scale, dtype, fixed = volume_arithmetic(cfg)
        fresh = cfg.use_gcp and cnn is None  # the CNN runs
        radius = cfg.matched_radius if fresh else 0
        # Kept buffers of another shape or type are let go now, before anything is allocated.
        kept = b.buffers(left.shape + (nd,), dtype, filter_size(left.shape, nd, radius))
        pair = b.upload(left, right, cfg.use_gcp or cfg.cost == 'sad')
        on_device: CnnConfidence | None = (b.to_device(cnn) if cfg.use_gcp and cnn is not None
                                           else None)
        lap(None if b.host else 'upload')
        if fresh:
            on_device = b.cnn_confidence(self.net, pair, nd, cfg.precision, radius, kept.scratch,
                                         seconds if timed or b.host else None, cancel)
            lap(None)  # the CNN timed its own stages
        volume = b.cost_volume(pair, nd, cfg.cost, cfg.window, scale or 1, dtype, kept.cost,
                               cancel)
        lap('cost')
        total = kept.total
        plain = gcp = sure = None
        if cfg.plain_sgm:  # into the path sums the GCPs' SGM then reuses
            total = b.aggregate(volume, fixed(cfg.p1), fixed(cfg.p2), PLAIN_PATHS, total, cancel)
            plain = b.disparity(total, cancel)
            lap('plain_sgm')
        if cfg.use_gcp:
            assert on_device is not None  # given (cnn) or computed (fresh)
            volume, gcp = b.select_refine(volume, on_device, cfg.theta, fixed(cfg.c_hi),
                                          fixed(cfg.c_low), cfg.gcp_lr_check,
                                          plain if cfg.gcp_plain_check else None)
            lap('refine')
        total = b.aggregate(volume, fixed(cfg.p1), fixed(cfg.p2), cfg.paths, total, cancel)
        b.keep(kept._replace(cost=volume.costs, total=total))
        lap('sgm')
        won = b.winners(total, cfg.subpixel, cancel)
        if cfg.median:
            won = won._replace(disparity=b.median(won.disparity))
        lap('wta')
        if self.fit is not None:
            sure = b.disparity_confidence(self.fit, won, on_device, gcp)
            lap('disparity_confidence')
        disp, sure = b.invalidate(won, sure, total, plain, cfg, camera)
        lap('invalidate')
        new_cnn = tuple(on_device) if fresh and on_device is not None else ()
        host = b.to_host(disp, won.consistent, won.margin, sure, gcp, *new_cnn)
        disp, consistent, m = cast(tuple[np.ndarray, np.ndarray, np.ndarray], host[:3])
        sure, gcp = host[3:5]
        if new_cnn:
            cnn = CnnConfidence(*host[5:])
        lap(None if b.host else 'download')
        cof_c, cof_d, cof_dr = cnn if cfg.use_gcp and cnn is not None else (None,) * 3
        if f > 1:  # back to full size, disparities in full-size pixels
            disp, consistent, m = (upsample(a, f, shape)
                                   for a in (disp * disp.dtype.type(f), consistent, m))
            cof_d, cof_dr = (None if a is None else a * a.dtype.type(f) for a in (cof_d, cof_dr))
            gcp, cof_c, cof_d, cof_dr, sure = (None if a is None else upsample(a, f, shape)
                                               for a in (gcp, cof_c, cof_d, cof_dr, sure))
            lap('upsample')
        call_glibc('malloc_trim', 0)  # the heap blocks this pair freed (see mmap_large_arrays)
        return StereoResult(disp, gcp, cof_c, cof_d, cof_dr, seconds, sure, consistent, m)
