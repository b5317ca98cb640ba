"""
The one stereo pipeline every caller uses: evaluation, the ROS node and the bag tools.

`StereoPipeline` runs the stages of a `stages.Backend` once, in order, over explicit
buffers: gray conversion -> alignment (`alignment`: the right view's vertical
misalignment undone) -> binning (``downsample``) -> upload -> CNN confidence -> cost
volume -> plain SGM -> GCP selection and refinement -> SGM -> winner-takes-all (and
median) -> disparity confidence -> invalidation (`postprocess`) -> one download of what is
published. Its settings are a `config.StereoConfig`, its memory is bounded by
`memory.memory_bytes`.
"""
from dataclasses import dataclass
import time
from typing import Any, NamedTuple

import numpy as np

from .alignment import correct, estimate, Misalignment
from .backend import backend
from .cancel import CancelFlag
from .cnn.filter import scratch_size
from .cnn.weights import confidence_fit
from .config import StereoConfig
from .costs import cost_spec
from .images import bin_area, gray_pair, subsample, upsample
from .memory import call_glibc, check_memory, volume_arithmetic
from .stages import Array, Backend, Buffers, CnnConfidence, CostVolume, Winners

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
        Wall time in seconds per stage that ran, in order: 'align' (estimate and
        correction), 'downsample', 'upload' (GPU), 'cnn' and 'confidence' (the CNN and its
        correlation), 'cost', 'plain_sgm', 'refine', 'sgm', 'wta', 'disparity_confidence',
        'invalidate', 'download' (GPU), 'upsample'.
    disparity_confidence : numpy.ndarray or None
        float32 (H, W) in [0, 1]: P(the published disparity within 3 px of the truth), 0
        where the disparity is NaN; None where no fit ships for the method and weights.
    consistent : numpy.ndarray
        bool (H, W): the right view's winner at x - d is within 1 px of d (x - d >= 0),
        whether or not ``lr_check`` invalidates by it.
    margin : numpy.ndarray
        float32 (H, W) in [0, 1]: the SGM cost margin 1 - S(winner) / S(rival).
    misalignment : Misalignment or None
        With ``align``: the right view's vertical misalignment v(x, y) over the
        (H, W) image (estimated on this pair, or the one given), known or not and why; its
        ``verdict()`` says whether the pair was corrected. None without ``align``.

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
    misalignment: Misalignment | None = None

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
                 timed: bool = False, misalignment: Misalignment | None = None
                 ) -> StereoResult:
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
        misalignment : Misalignment, optional
            With ``align``, the misalignment to undo instead of estimating this
            pair's (the node's, smoothed over frames); `alignment.correct` decides whether
            it is (an unknown one: the pair stays as it is). Ignored without ``align``.

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
        cfg = self.config
        reused = _reused_cnn(cnn) if cfg.use_gcp else None
        run = _Run(self.backend, cancel, timed)
        left, right = gray_pair(left, right)
        check_memory(cfg, *left.shape)
        shape = left.shape
        if cfg.align:
            right, misalignment = self._align(left, right, misalignment, run)
        if cfg.downsample > 1:
            left, right, reused = self._to_matching_grid(left, right, reused, run)
        published = self._match(left, right, reused, camera, run)
        if cfg.use_gcp and reused is not None:  # the CNN did not run: its outputs are the input's
            published = published._replace(cnn=reused)
        if cfg.downsample > 1:
            published = self._to_input_grid(published, shape, run)
        call_glibc('malloc_trim', 0)  # the heap blocks this pair freed (see mmap_large_arrays)
        cof_c, cof_d, cof_dr = published.cnn or (None, None, None)
        return StereoResult(disparity=published.disparity, gcp=published.gcp, cof_c=cof_c,
                            cof_d=cof_d, cof_dr=cof_dr, seconds=run.seconds,
                            disparity_confidence=published.confidence,
                            consistent=published.consistent, margin=published.margin,
                            misalignment=misalignment if cfg.align else None)

    def _align(self, left: np.ndarray, right: np.ndarray, given: Misalignment | None,
               run: '_Run') -> tuple[np.ndarray, Misalignment]:
        """Return the right image with the misalignment undone where it is, and the estimate."""
        run.lap(None)
        found = given if given is not None else estimate(left, right, self.config.max_disp)
        right = np.asarray(correct(right, found))
        run.lap('align')
        return right, found

    def _match(self, left: np.ndarray, right: np.ndarray, reused: CnnConfidence | None,
               camera: tuple[float, float] | None, run: '_Run') -> '_Published':
        """Run the method on the matching grid; return what is published, on the host."""
        cfg, b = self.config, self.backend
        scale, dtype, run.fixed = volume_arithmetic(cfg)
        fresh = cfg.use_gcp and reused is None
        radius = cfg.matched_radius if fresh else 0
        shape = left.shape + (cfg.matched_disp,)
        # Kept buffers of another shape or type are let go now, before anything is allocated.
        run.kept = b.buffers(shape, dtype, filter_size(left.shape, shape[2], radius))
        pair = b.upload(left, right, cfg.use_gcp or cost_spec(cfg.cost).standardized)
        cnn = b.to_device(reused) if reused is not None else None
        run.lap(None if b.host else 'upload')
        if fresh:
            cnn = self._cnn_confidence(pair, radius, run)
        volume = self._cost_volume(pair, scale or 1, dtype, run)
        plain = self._plain_sgm(volume, run) if cfg.plain_sgm else None
        gcps = None
        if cfg.use_gcp:
            assert cnn is not None  # given (reused) or computed (fresh)
            volume, gcps = self._refine(volume, cnn, plain, run)
        total = self._sgm(volume, run)
        winners = self._winners(total, run)
        confidence = self._disparity_confidence(winners, cnn, gcps, run)
        disparity, confidence = b.invalidate(winners, confidence, total, plain, cfg, camera)
        run.lap('invalidate')
        published = _Published(disparity, winners.consistent, winners.margin, confidence, gcps,
                               cnn if fresh else None)
        return self._download(published, run)

    def _cnn_confidence(self, pair: Any, radius: int, run: '_Run') -> CnnConfidence:
        """Return the CNN confidence of the pair (timed by the CNN's own stages)."""
        b, cfg = self.backend, self.config
        cnn = b.cnn_confidence(self.net, pair, cfg.matched_disp, cfg.precision, radius,
                               run.kept.scratch, run.seconds if run.timed or b.host else None,
                               run.cancel)
        run.lap(None)
        return cnn

    def _cost_volume(self, pair: Any, scale: int, dtype: np.dtype, run: '_Run') -> CostVolume:
        """Return the matching cost volume, into the kept buffer."""
        cfg = self.config
        volume = self.backend.cost_volume(pair, cfg.matched_disp, cfg.cost, cfg.window, scale,
                                          dtype, run.kept.cost, run.cancel)
        run.lap('cost')
        return volume

    def _plain_sgm(self, volume: CostVolume, run: '_Run') -> Array:
        """Return plain SGM's disparity (PLAIN_PATHS, no GCPs), summed into the kept buffer."""
        b, cfg = self.backend, self.config
        total = b.aggregate(volume, run.fixed(cfg.p1), run.fixed(cfg.p2), PLAIN_PATHS,
                            run.kept.total, run.cancel)
        run.kept = run.kept._replace(total=total)  # the GCPs' SGM then sums into it again
        plain = b.disparity(total, run.cancel)
        run.lap('plain_sgm')
        return plain

    def _refine(self, volume: CostVolume, cnn: CnnConfidence, plain: Array | None,
                run: '_Run') -> tuple[CostVolume, Array]:
        """Return the volume refined by the GCPs above theta, and the GCPs."""
        cfg = self.config
        refined = self.backend.select_refine(volume, cnn, cfg.theta, run.fixed(cfg.c_hi),
                                             run.fixed(cfg.c_low), cfg.gcp_lr_check,
                                             plain if cfg.gcp_plain_check else None)
        run.lap('refine')
        return refined

    def _sgm(self, volume: CostVolume, run: '_Run') -> Array:
        """Return the summed path costs of `volume`; keep both volumes for the next pair."""
        b, cfg = self.backend, self.config
        total = b.aggregate(volume, run.fixed(cfg.p1), run.fixed(cfg.p2), cfg.paths,
                            run.kept.total, run.cancel)
        b.keep(run.kept._replace(cost=volume.costs, total=total))
        run.lap('sgm')
        return total

    def _winners(self, total: Array, run: '_Run') -> Winners:
        """Return the winner-takes-all of the summed costs, with the median if set."""
        b = self.backend
        winners = b.winners(total, self.config.subpixel, run.cancel)
        if self.config.median:
            winners = winners._replace(disparity=b.median(winners.disparity))
        run.lap('wta')
        return winners

    def _disparity_confidence(self, winners: Winners, cnn: CnnConfidence | None,
                              gcps: Array | None, run: '_Run') -> Array | None:
        """Return P(within 3 px) of each winner, None where no fit ships."""
        if self.fit is None:
            return None
        confidence = self.backend.disparity_confidence(self.fit, winners, cnn, gcps)
        run.lap('disparity_confidence')
        return confidence

    def _download(self, published: '_Published', run: '_Run') -> '_Published':
        """Return `published` on the host, in one download."""
        b = self.backend
        arrays = b.to_host(*published[:5], *(published.cnn or ()))
        disparity, consistent, margin, confidence, gcps = arrays[:5]
        cnn = CnnConfidence(*arrays[5:]) if published.cnn is not None else None
        run.lap(None if b.host else 'download')
        return _Published(disparity, consistent, margin, confidence, gcps, cnn)

    def _to_matching_grid(self, left: np.ndarray, right: np.ndarray,
                          reused: CnnConfidence | None, run: '_Run'
                          ) -> tuple[np.ndarray, np.ndarray, CnnConfidence | None]:
        """Return the pair binned by `downsample`, and reused CNN outputs taken to its grid."""
        f = self.config.downsample
        left, right = bin_area(left, f), bin_area(right, f)
        if reused is not None:  # undo the upsampling of their run
            cof_c, cof_d, cof_dr = (subsample(a, f, left.shape) for a in reused)
            reused = CnnConfidence(cof_c, cof_d // f, cof_dr // f)
        run.lap('downsample')
        return left, right, reused

    def _to_input_grid(self, published: '_Published', shape: tuple[int, ...],
                       run: '_Run') -> '_Published':
        """Return `published` blown up to the input's `shape`, disparities in its pixels."""
        f = self.config.downsample

        def up(a: np.ndarray | None, disparity: bool = False) -> np.ndarray | None:
            """Return `a` at the input's size (None stays None); a disparity times f."""
            if a is None:
                return None
            return upsample(a * a.dtype.type(f) if disparity else a, f, shape)

        cnn = published.cnn
        if cnn is not None:
            cnn = CnnConfidence(up(cnn.cof_c), up(cnn.cof_d, True), up(cnn.cof_dr, True))
        full = _Published(up(published.disparity, True), up(published.consistent),
                          up(published.margin), up(published.confidence), up(published.gcp),
                          cnn)
        run.lap('upsample')
        return full


class _Published(NamedTuple):
    """What one pair publishes, each (H, W): on the device, then the host (`StereoResult`)."""

    disparity: Any
    consistent: Any
    margin: Any
    confidence: Any  # None where no confidence fit ships
    gcp: Any  # None without GCPs
    cnn: CnnConfidence | None  # the CNN's outputs where it ran (or was reused), else None


class _Run:
    """One pair's run: its stage clock, its cancel flag and the buffers and units it uses."""

    def __init__(self, b: Backend, cancel: CancelFlag | None, timed: bool) -> None:
        """Start the clock; `timed`: wait for the device at each stage's end."""
        self.backend, self.cancel, self.timed = b, cancel, timed
        self.seconds: dict[str, float] = {}
        self.kept = Buffers(None, None, None)
        self.fixed: Any = None  # a cost-unit value in the volume's units (volume_arithmetic)
        self._start = time.perf_counter()

    def lap(self, stage: str | None) -> None:
        """Record the time since the last lap as `stage` (None: only restart the clock)."""
        if self.timed:
            self.backend.synchronize()
        now = time.perf_counter()
        if stage is not None:
            self.seconds[stage] = now - self._start
        self._start = now
        if self.cancel is not None:
            self.cancel.check()


def _reused_cnn(cnn: Any) -> CnnConfidence | None:
    """Return `StereoPipeline.__call__`'s `cnn` as a CnnConfidence; ValueError if malformed."""
    if cnn is None:
        return None
    if len(cnn) != 3:
        raise ValueError('cnn must be (cof_c, cof_d, cof_dr), as StereoResult.cnn holds them')
    return CnnConfidence(*cnn)
