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
from .config import StereoConfig
from .gcp import refine, select
from .images import bin_area, gray_pair, mean_std, upsample
from .memory import call_glibc, check_memory, volume_arithmetic
from .postprocess import Confidence, features, invalidate, margin
from .sgm import aggregate, winners


@dataclass
class StereoResult:
    disparity: np.ndarray  # float32 (H, W), NaN where invalid
    gcp: np.ndarray | None  # bool (H, W) GCP mask, None without GCPs
    cof_c: np.ndarray | None  # float32 (H, W) CNN confidence max_d Vol
    cof_d: np.ndarray | None  # int32 (H, W) CNN disparity argmax_d Vol
    cof_dr: np.ndarray | None  # int32 (H, W) right view's CNN disparity (see cnn.confidence)
    seconds: dict  # wall time per stage
    # float32 (H, W) P(disparity within 3 px of the truth) (postprocess.Confidence), 0 where
    # not published; None where no fit exists for the method and weights
    confidence: np.ndarray | None = None
    consistent: np.ndarray | None = None  # bool (H, W) left-right agreement (sgm.winners)
    margin: np.ndarray | None = None  # float32 (H, W) SGM cost margin (postprocess.margin)


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
        self.config = (config or StereoConfig()).validate()
        if self.config.device != 'cpu':
            from .gpu import check_device
            check_device(self.config.device)
        self._net = net
        self._workspace = {} if _workspace is None else _workspace
        self.fit = Confidence.load(self.config)  # the confidence fit, None if none

    def with_config(self, config):
        """
        Return a pipeline for `config` that keeps this one's arrays and, if it can, its CNN.

        The CNN is kept when weights and device match; the arrays always are (the two
        pipelines must then not run at the same time).
        """
        same = (config.weights, config.device) == (self.config.weights, self.config.device)
        return StereoPipeline(config, self._net if same else None, self._workspace)

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
        if self._net is None:
            from .cnn import load_net  # torch is imported only when GCPs are used
            device = self.config.device
            if device != 'cpu':
                from .gpu import torch_device
                device = torch_device(device)
            self._net = load_net(self.config.weights or None, device)
        return self._net

    def __call__(self, left, right, confidence=None, cancel=None, camera=None):
        """
        Return the StereoResult of a pair.

        `confidence`: (cof_c, cof_d, cof_dr) of an earlier run on the same pair, max_disp and
        downsample, as its StereoResult holds them, to sweep GCP/SGM parameters without
        running the CNN again. `cancel`: a CancelFlag that another thread may set to stop the
        run (raises Cancelled within a row of a CPU kernel or a CNN layer). `camera`: (f * T
        in px m, cx_left - cx_right in px) for min_depth / max_depth (None: not applied).
        Raises ValueError for bad input or a pair that needs more than memory_limit_mb.
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
                h, w = left.shape
                cof_c, cof_d, cof_dr = (np.asarray(a)[:h * f:f, :w * f:f] for a in confidence)
                confidence = cof_c, cof_d // f, cof_dr // f
            lap('downsample')
        confidence = confidence if cfg.use_gcp else None
        if cfg.device == 'cpu':
            outputs = self._match(left, right, confidence, lap, seconds, cancel)
        else:
            outputs = self._match_cuda(left, right, confidence, lap, seconds)
        disp, consistent, s_best, s_second, gcp, cof_c, cof_d, cof_dr = outputs
        m = margin(s_best, s_second)
        del s_best, s_second
        if cfg.median:
            disp = cv2.medianBlur(disp, 3)
        if f > 1:  # back to full size, disparities in full-size pixels
            disp, cof_d, cof_dr = (None if a is None else a * a.dtype.type(f)
                                   for a in (disp, cof_d, cof_dr))
            disp, consistent, m, gcp, cof_c, cof_d, cof_dr = (
                None if a is None else upsample(a, f, shape)
                for a in (disp, consistent, m, gcp, cof_c, cof_d, cof_dr))
            lap('upsample')
        sure = None
        if self.fit is not None:
            sure = self.fit(features(disp, consistent, m, cof_c, cof_d, gcp))
            lap('disparity_confidence')
        invalidate(disp, consistent, m, cfg, camera, sure)
        if sure is not None:
            sure[np.isnan(disp)] = 0.0
        lap('invalidate')
        call_glibc('malloc_trim', 0)  # the heap blocks this pair freed (see mmap_large_arrays)
        return StereoResult(disp, gcp, cof_c, cof_d, cof_dr, seconds, sure, consistent, m)

    def _match(self, left, right, confidence, lap, seconds, cancel):
        """
        Return (disparity, consistent, s_best, s_second, gcp, cof_c, cof_d, cof_dr), on the CPU.

        The first four are `sgm.winners`' outputs (the left-right agreement always computed,
        for the confidence).
        """
        cfg = self.config
        nd = cfg.matched_disp
        shape = left.shape + (nd,)
        scale, dtype, fixed = volume_arithmetic(cfg)
        # Kept arrays of another shape or type are let go now, before anything is allocated.
        kept = {name: self._array(name, shape, dtype) for name in ('cost', 'total')}
        gcp = cof_c = cof_d = cof_dr = None
        if cfg.use_gcp:
            if confidence is None:
                from .cnn import confidence as cnn_confidence
                confidence = cnn_confidence(self.net, left, right, nd, cfg.device, cfg.bf16,
                                            seconds=seconds, cancel=cancel)
                lap(None)  # the CNN timed its own stages
            cof_c, cof_d, cof_dr = confidence
        volume = cost_mod.cost_volume(left, right, nd, cfg.cost, cfg.window, kept['cost'],
                                      scale or 1, dtype, cancel)
        lap('cost')
        if cfg.use_gcp:
            gcp = select(cof_c, cof_d, cof_dr, cfg.theta, cfg.gcp_lr_check)
            refine(volume, gcp, cof_d, fixed(cfg.c_hi), fixed(cfg.c_low))
            lap('refine')
        total = aggregate(volume, fixed(cfg.p1), fixed(cfg.p2), cfg.paths, kept['total'],
                          cancel)
        self._workspace.update(cost=volume, total=total)
        lap('sgm')
        wta = winners(total, cfg.subpixel, True, cancel)
        lap('wta')
        return (*wta, gcp, cof_c, cof_d, cof_dr)

    def _match_cuda(self, left, right, confidence, lap, seconds):
        """
        Return `_match`'s outputs, computed on the GPU `config.device` (see `gpu`).

        One upload of the pair (and of `confidence` if given), the volumes stay in GPU
        memory, one download of the outputs. The device is synchronized at each stage's end,
        so that the stage times are the GPU's.
        """
        import torch

        from . import gpu
        from .cnn import device_confidence, padded_input
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
                                        seconds)
                lap(None)  # the CNN timed its own stages
            volume = cost_volume(pair if cfg.cost == 'census' else standardized, nd, cfg.cost,
                                 cfg.window, self._array('cuda_cost', shape, vtype),
                                 scale or 1, dtype)
            top = cost_mod.max_cost(cfg.cost, cfg.window) * (scale or 1)
            stage('cost')
            gcp = None
            if cfg.use_gcp:
                gcp = select_refine(volume, *cof, cfg.theta, fixed(cfg.c_hi), fixed(cfg.c_low),
                                    cfg.gcp_lr_check)
                top = max(top, fixed(cfg.c_hi))
                stage('refine')
            total = aggregate(volume, fixed(cfg.p1), fixed(cfg.p2), cfg.paths, top,
                              self._array('cuda_total', shape, vtype))
            self._workspace.update(cuda_cost=volume, cuda_total=total)
            stage('sgm')
            wta = winners(total, cfg.subpixel, True)  # disp, consistent, s_best, s_second
            stage('wta')
            fresh = cof if cfg.use_gcp and confidence is None else []
            wta, fresh = ([a.cpu().numpy() for a in arrays] for arrays in (wta, fresh))
            gcp = None if gcp is None else gcp.cpu().numpy()
            lap('download')
        cof_c, cof_d, cof_dr = fresh or confidence or (None,) * 3
        return (*wta, gcp, cof_c, cof_d, cof_dr)
