"""
The one stereo pipeline every caller uses: evaluation, the ROS node and the bag tools.

cost volume -> (CNN confidence -> GCPs -> refinement) -> SGM -> winner-takes-all ->
invalidation and confidence (`postprocess`). Its settings are a `config.StereoConfig`, its
memory is bounded by `memory.memory_bytes`.
"""
from dataclasses import dataclass
import time

import cv2
import numpy as np

from . import cost as cost_mod
from .cnn_filter import scratch_size
from .config import StereoConfig
from .gcp import refine, select
from .images import bin_area, gray_pair, mean_std, subsample, upsample
from .memory import call_glibc, check_memory, volume_arithmetic
from .postprocess import Confidence, features, invalidate, margin
from .sgm import aggregate, costs_at, winners

# The paths of plain SGM for `plain_check` and `gcp_plain_check` (horizontal and
# vertical): on the validation frames as good a second opinion as 16, in a quarter of the
# time (doc/published.md).
PLAIN_PATHS = 4


def filter_size(shape, max_disp, radius):
    """Return the float32 values the CNN filter holds for a pair of `shape` (0 without it)."""
    if not radius:
        return 0
    from .cnn import STRIP_ROWS  # torch is imported only when GCPs are used
    return scratch_size(*shape, max_disp, radius, STRIP_ROWS)


@dataclass
class StereoResult:
    """
    What `StereoPipeline` returns for one pair: the disparity and what it was made from.

    Every array is (H, W), the size of the input images (with ``downsample`` > 1 blown
    back up to it), row y, column x of the left image. Disparities are in pixels of the
    input images: the left pixel (x, y) matches the right pixel (x - d, y). Invalid
    disparities are NaN (not 0, not negative).

    Attributes
    ----------
    disparity : numpy.ndarray
        float32 (H, W), px, in [0, max_disp - 1]; sub-pixel with ``subpixel``; NaN where
        the invalidation (``stereo.postprocess``: valid_window, uniqueness_ratio, speckles,
        depth limits, min_confidence, lr_check) rejected the winner.
    gcp : numpy.ndarray or None
        bool (H, W): the ground control points (pixels whose CNN disparity steered SGM);
        None without ``use_gcp``.
    cof_c : numpy.ndarray or None
        float32 (H, W) in [0, 1]: the calibrated CNN confidence of its best disparity (the
        probability that ``cof_d`` is within 1 px of the truth, compared with theta); None
        without ``use_gcp``.
    cof_d : numpy.ndarray or None
        int32 (H, W), px: the CNN's best disparity; None without ``use_gcp``.
    cof_dr : numpy.ndarray or None
        int32 (H, W), px: the right view's CNN disparity at each right pixel (for
        ``gcp_lr_check``); None without ``use_gcp``. Pass ``(cof_c, cof_d, cof_dr)`` as
        `StereoPipeline.__call__`'s `confidence` to skip the CNN on the same pair.
    seconds : dict
        Wall time in seconds per stage, {stage name: float}, in the order run. Stages
        (each only when it ran): 'downsample', 'upload' (GPU), 'cnn' and 'confidence'
        (the CNN's convolutions and correlation), 'cost', 'refine' (GCPs), 'sgm', 'wta',
        'download' (GPU), 'disparity_confidence', 'invalidate', 'upsample'.
    confidence : numpy.ndarray or None
        float32 (H, W) in [0, 1]: the calibrated probability that the published disparity
        is within 3 px of the truth (``postprocess.Confidence``), 0 where the disparity is
        NaN; None where no fit ships for the method and weights (the fit is beside the
        weights, ``<weights>.confidence.json``).
    consistent : numpy.ndarray
        bool (H, W): the left-right agreement, False where the right view's winner at
        x - d is more than 1 px from d or x - d < 0 (``sgm.winners``); computed whether
        or not ``lr_check`` invalidates by it.
    margin : numpy.ndarray
        float32 (H, W) in [0, 1]: the SGM cost margin 1 - S(winner) / S(rival), the
        rival the least summed cost more than 1 px from the winner; 1 where there is none
        (``postprocess.margin``).

    """

    disparity: np.ndarray
    gcp: np.ndarray | None
    cof_c: np.ndarray | None
    cof_d: np.ndarray | None
    cof_dr: np.ndarray | None
    seconds: dict
    confidence: np.ndarray | None = None
    consistent: np.ndarray | None = None
    margin: np.ndarray | None = None


class StereoPipeline:
    """
    Runs a StereoConfig on image pairs; the CNN is loaded once, on first use.

    The cost volume and the summed path costs are written into two arrays kept from the
    previous call of the same size and type (two fresh (H, W, D) arrays per frame would cost
    a page fault per 4 KiB); kept arrays that do not fit a pair are let go before new ones
    are allocated, and `release` lets them all go. So one pipeline serves one thread at a
    time.
    """

    def __init__(self, config=None, net=None, _workspace=None):
        self.config = config or StereoConfig()  # checked when it was made
        if self.config.device != 'cpu':
            from .gpu import check_device
            check_device(self.config.device)
        self._net = net
        self._workspace = {} if _workspace is None else _workspace
        self.fit = Confidence.load(self.config)  # the confidence fit, None if none

    def with_config(self, config):
        """
        Return a pipeline for `config` that keeps this one's arrays and, if it can, its CNN.

        The CNN is kept when weights and device match, the arrays when the device does (the
        two pipelines must then not run at the same time); another device starts without
        arrays, and this one's go when it does.
        """
        device = config.device == self.config.device
        same = device and config.weights == self.config.weights
        return StereoPipeline(config, self._net if same else None,
                              self._workspace if device else None)

    def _array(self, name, shape, dtype):
        """
        Return the kept array `name` if it has `shape` and `dtype`, else None.

        With None the callee allocates; a kept array of another shape or type is let go here,
        and the new one is kept then.
        """
        a = self._workspace.get(name)
        if a is not None and a.shape == shape and a.dtype == dtype:
            return a
        self._workspace.pop(name, None)
        return None

    def release(self):
        """Let go of the kept arrays (of every pipeline sharing them), e.g. when idle."""
        self._workspace.clear()
        call_glibc('malloc_trim', 0)  # kept arrays below MMAP_BYTES were heap blocks

    @property
    def net(self):
        """
        Return the CNN, loaded on first use.

        ValueError if its weights have no calibration for the config's matched_radius.
        """
        from .cnn import calibration, load_net  # torch is imported only when GCPs are used
        if self._net is None:
            device = self.config.device
            if device != 'cpu':
                from .gpu import torch_device
                device = torch_device(device)
            self._net = load_net(self.config.weights or None, device)
        calibration(self._net, self.config.matched_radius)
        return self._net

    def __call__(self, left, right, confidence=None, cancel=None, camera=None):
        """
        Return the `StereoResult` of one rectified pair.

        Parameters
        ----------
        left, right : numpy.ndarray
            The rectified left and right images, of one size (H, W): gray (H, W) or
            (H, W, 1), RGB (H, W, 3) or RGBA (H, W, 4, alpha ignored), in RGB channel order
            (convert OpenCV's BGR first); integer (uint8, uint16) or float (any scale:
            every cost and the CNN standardize or compare within an image), finite values
            only. Colour is turned into gray (BT.601 luma). The two may differ in dtype and
            in gray or colour. W must be at least max_disp / downsample.
        confidence : tuple of numpy.ndarray, optional
            (cof_c, cof_d, cof_dr) of an earlier run on the same pair, max_disp and
            downsample, as its StereoResult holds them, to sweep GCP or SGM settings
            without running the CNN again (ignored without ``use_gcp``).
        cancel : CancelFlag, optional
            Another thread may set it to stop the run: raises ``cancel.Cancelled`` within
            a row of a CPU kernel or a CNN layer.
        camera : tuple of float, optional
            (f * T in px m, cx_left - cx_right in px), the depth Z = f * T / (d - offset) of
            a disparity d, for min_depth and max_depth; None: those limits are not applied.

        Returns
        -------
        StereoResult
            The disparity in px of the input images (NaN where invalid) and the maps it
            was made from, each (H, W); `seconds` holds each stage's wall time.

        Raises
        ------
        ValueError
            For images it cannot take (shape, dtype, NaN, unequal sizes, narrower than the
            disparity range, naming which) or a pair that would need more than
            memory_limit_mb, saying what to lower.

        """
        cfg = self.config
        if cfg.use_gcp and confidence is not None and len(confidence) != 3:
            raise ValueError('confidence must be (cof_c, cof_d, cof_dr), '
                             'as StereoResult holds them')
        seconds = {}
        t = time.perf_counter()

        def lap(stage):
            """Record the time since the last lap as `stage`; None only restarts the clock."""
            nonlocal t
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
            if cfg.use_gcp and confidence is not None:  # undo the upsampling of its run
                cof_c, cof_d, cof_dr = (subsample(a, f, left.shape) for a in confidence)
                confidence = cof_c, cof_d // f, cof_dr // f
            lap('downsample')
        confidence = confidence if cfg.use_gcp else None
        if cfg.device == 'cpu':
            outputs = self._match(left, right, confidence, lap, seconds, cancel)
        else:
            outputs = self._match_cuda(left, right, confidence, lap, seconds)
        disp, consistent, m, sure, gcp, cof_c, cof_d, cof_dr, plain = outputs
        if cfg.median:
            disp = cv2.medianBlur(disp, 3)
        if self.fit is not None and sure is None:
            sure = self.fit(features(disp, consistent, m, cof_c, cof_d, gcp))
            lap('disparity_confidence')
        invalidate(disp, consistent, m, cfg, camera, sure, self.summed_costs, plain)
        if sure is not None:
            sure[np.isnan(disp)] = 0.0
        lap('invalidate')
        if f > 1:  # back to full size, disparities in full-size pixels
            disp, cof_d, cof_dr = (None if a is None else a * a.dtype.type(f)
                                   for a in (disp, cof_d, cof_dr))
            disp, consistent, m, gcp, cof_c, cof_d, cof_dr, sure = (
                None if a is None else upsample(a, f, shape)
                for a in (disp, consistent, m, gcp, cof_c, cof_d, cof_dr, sure))
            lap('upsample')
        call_glibc('malloc_trim', 0)  # the heap blocks this pair freed (see mmap_large_arrays)
        return StereoResult(disp, gcp, cof_c, cof_d, cof_dr, seconds, sure, consistent, m)

    def summed_costs(self, rows, cols, disparities):
        """
        Return the summed SGM costs of pixels at given disparities, of the pair matched last.

        Pixel i is (rows[i], cols[i]) of the matching grid, intp (n,); `disparities` intp
        (n, k), each in [0, matched_disp - 1]; returns (n, k) of the volume's type (uint16
        fixed point or float32), read from the kept path sums (on the GPU with a CUDA
        device). For `postprocess.background_fits`.
        """
        if self.config.device == 'cpu':
            return costs_at(self._workspace['total'], rows, cols, disparities)
        import torch
        total = self._workspace['cuda_total']
        fixed = total.dtype == torch.uint16  # read as int16, the same bits
        index = [torch.from_numpy(np.ascontiguousarray(a, np.int64)).to(total.device)
                 for a in (rows[:, None], cols[:, None], disparities)]
        picked = (total.view(torch.int16) if fixed else total)[tuple(index)].cpu().numpy()
        return picked.view(np.uint16) if fixed else picked

    def _match(self, left, right, confidence, lap, seconds, cancel):
        """
        Return (disparity, consistent, margin, sure, gcp, cof_c, cof_d, cof_dr, plain).

        On the CPU. The disparity and the left-right agreement (always computed, for the
        confidence) are `sgm.winners`', `margin` the `postprocess.margin` of its costs;
        `sure`: the calibrated confidence, None here (the caller computes it, after the
        median); `plain`: the integer disparity of SGM on the costs before the GCPs refine
        them, for `gcp_plain_check` and `plain_check` (None without both or without GCPs).
        """
        cfg = self.config
        nd = cfg.matched_disp
        shape = left.shape + (nd,)
        scale, dtype, fixed = volume_arithmetic(cfg)
        # Kept arrays of another shape or type are let go now, before anything is allocated.
        kept = {name: self._array(name, shape, dtype) for name in ('cost', 'total')}
        radius = cfg.matched_radius if cfg.use_gcp else 0
        # The CNN filter's rows (cnn_filter.StripFilter), kept too; None (let go) without it.
        size = filter_size(left.shape, nd, radius)
        scratch = self._array('cnn_filter', (size,), np.float32)
        gcp = cof_c = cof_d = cof_dr = None
        if cfg.use_gcp:
            if confidence is None:
                from .cnn import confidence as cnn_confidence
                if radius and scratch is None:
                    scratch = np.empty(size, np.float32)
                    self._workspace['cnn_filter'] = scratch
                confidence = cnn_confidence(self.net, left, right, nd, cfg.device, cfg.bf16,
                                            seconds=seconds, cancel=cancel, radius=radius,
                                            scratch=scratch)
                lap(None)  # the CNN timed its own stages
            cof_c, cof_d, cof_dr = confidence
        volume = cost_mod.cost_volume(left, right, nd, cfg.cost, cfg.window, kept['cost'],
                                      scale or 1, dtype, cancel)
        lap('cost')
        total, plain = kept['total'], None
        if cfg.plain_sgm:  # into the path sums the GCPs' SGM then reuses
            total = aggregate(volume, fixed(cfg.p1), fixed(cfg.p2), PLAIN_PATHS, total, cancel)
            plain = winners(total, False, False, cancel)[0]
            lap('plain_sgm')
        if cfg.use_gcp:
            gcp = select(cof_c, cof_d, cof_dr, cfg.theta, cfg.gcp_lr_check,
                         plain if cfg.gcp_plain_check else None)
            refine(volume, gcp, cof_d, fixed(cfg.c_hi), fixed(cfg.c_low))
            lap('refine')
        total = aggregate(volume, fixed(cfg.p1), fixed(cfg.p2), cfg.paths, total, cancel)
        self._workspace.update(cost=volume, total=total)
        lap('sgm')
        disp, consistent, s_best, s_second = winners(total, cfg.subpixel, True, cancel)
        lap('wta')
        return (disp, consistent, margin(s_best, s_second), None, gcp, cof_c, cof_d, cof_dr,
                plain)

    def _match_cuda(self, left, right, confidence, lap, seconds):
        """
        Return `_match`'s outputs, computed on the GPU `config.device` (see `gpu`).

        One upload of the pair (and of `confidence` if given), the volumes stay in GPU
        memory, one download of the outputs. The device is synchronized at each stage's end,
        so that the stage times are the GPU's. The calibrated confidence is computed there
        too (`postprocess_cuda`), except with `median`, which runs on the host before it.
        """
        import torch

        from . import gpu, postprocess_cuda
        from .cnn import padded_input
        from .cnn_cuda import device_confidence
        from .cost_cuda import cost_volume
        from .gcp_cuda import select_refine
        from .sgm_cuda import aggregate, winners

        def stage(name):
            gpu.synchronize()
            lap(name)

        cfg = self.config
        nd = cfg.matched_disp
        scale, dtype, fixed = volume_arithmetic(cfg)
        shape, vtype = left.shape + (nd,), gpu.VOLUME_TYPES[dtype]
        device = gpu.torch_device(cfg.device)
        with gpu.current(cfg.device):
            stats = [mean_std(g) for g in (left, right)]
            pair = torch.from_numpy(np.stack([left, right])).to(device)
            if cfg.use_gcp and confidence is not None:
                cof = [torch.from_numpy(np.ascontiguousarray(a, t)).to(device)
                       for a, t in zip(confidence, (np.float32, np.int32, np.int32))]
            stage('upload')
            if cfg.use_gcp or cfg.cost == 'sad':  # images.standardize on the device
                standardized = torch.stack([(g - m) / s for g, (m, s) in zip(pair, stats)])
            if cfg.use_gcp and confidence is None:
                cof = device_confidence(self.net, padded_input(standardized), nd, cfg.bf16,
                                        seconds, cfg.matched_radius)
                lap(None)  # the CNN timed its own stages
            volume = cost_volume(pair if cfg.cost == 'census' else standardized, nd, cfg.cost,
                                 cfg.window, self._array('cuda_cost', shape, vtype),
                                 scale or 1, dtype)
            top = cost_mod.max_cost(cfg.cost, cfg.window) * (scale or 1)
            stage('cost')
            gcp = plain = sure = None
            total = self._array('cuda_total', shape, vtype)
            if cfg.plain_sgm:  # into the path sums the GCPs' SGM then reuses
                total = aggregate(volume, fixed(cfg.p1), fixed(cfg.p2), PLAIN_PATHS, top, total)
                plain = winners(total)[0]
                stage('plain_sgm')
            if cfg.use_gcp:
                gcp = select_refine(volume, *cof, cfg.theta, fixed(cfg.c_hi), fixed(cfg.c_low),
                                    cfg.gcp_lr_check, plain if cfg.gcp_plain_check else None)
                top = max(top, fixed(cfg.c_hi))
                stage('refine')
            total = aggregate(volume, fixed(cfg.p1), fixed(cfg.p2), cfg.paths, top, total)
            self._workspace.update(cuda_cost=volume, cuda_total=total)
            stage('sgm')
            disp, consistent, s_best, s_second = winners(total, cfg.subpixel, True)
            m = postprocess_cuda.margin(s_best, s_second)
            stage('wta')
            if self.fit is not None and not cfg.median:
                sure = postprocess_cuda.calibrated(self.fit, postprocess_cuda.features(
                    disp, consistent, m, *(cof[:2] if cfg.use_gcp else (None, None)), gcp))
                stage('disparity_confidence')
            fresh = cof if cfg.use_gcp and confidence is None else []
            disp, consistent, m, sure, gcp, plain, *fresh = (
                None if a is None else a.cpu().numpy()
                for a in (disp, consistent, m, sure, gcp, plain, *fresh))
            lap('download')
        cof_c, cof_d, cof_dr = fresh or confidence or (None,) * 3
        return disp, consistent, m, sure, gcp, cof_c, cof_d, cof_dr, plain
