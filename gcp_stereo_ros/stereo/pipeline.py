"""
The one stereo pipeline every caller uses: evaluation, the ROS node and the bag tools.

cost volume -> (CNN confidence -> GCPs -> refinement) -> SGM -> winner-takes-all.
"""
import ctypes
import dataclasses
from dataclasses import dataclass
import math
import re
import time

import cv2
import numpy as np

from . import cost as cost_mod
from .gcp import refine, select
from .images import bin_area, gray_pair, mean_std, upsample
from .postprocess import Confidence, features, invalidate, margin
from .sgm import aggregate, directions, path_sum_bound, PATHS, winners

MIB = 1 << 20

# Defaults for each matching cost, chosen by cross-validation on the validation frames
# (README: "Method and results"); theta is on the calibrated scale (cnn.calibrated).
COST_DEFAULTS = {
    'census': {'p1': 8.0, 'p2': 128.0, 'theta': 0.3, 'c_hi': 200.0, 'c_low': 5.0,
               'gcp_lr_check': True},
    'sad': {'p1': 0.02, 'p2': 0.5, 'theta': 0.45, 'c_hi': 5.0, 'c_low': 0.001,
            'gcp_lr_check': True},
}
# The paper's values (Zhong et al., section 4): its theta is read on our calibrated scale.
PAPER = {
    'census': {'p1': 4.0, 'p2': 128.0, 'theta': 0.60, 'c_hi': 200.0, 'c_low': 1.3,
               'gcp_lr_check': False},
    'sad': {'p1': 1.0, 'p2': 14.0, 'theta': 0.55, 'c_hi': 5.0, 'c_low': 0.001,
            'gcp_lr_check': False},
}
# Every invalidation off (stereo.postprocess). The paper published every integer WTA
# disparity: its preset has this and no sub-pixel fit.
UNFILTERED = {'valid_window': False, 'lr_check': False, 'uniqueness_ratio': 0.0,
              'speckle_size': 0, 'min_depth': 0.0, 'max_depth': 0.0, 'min_confidence': 0.0}
PAPER = {cost: {**values, **UNFILTERED, 'subpixel': False} for cost, values in PAPER.items()}
PRESETS = {'default': COST_DEFAULTS, 'paper': PAPER}
DOWNSAMPLE = (1, 2, 4)


@dataclass(frozen=True)
class StereoConfig:
    cost: str = 'census'
    window: int = 9
    max_disp: int = 128
    p1: float = COST_DEFAULTS['census']['p1']
    p2: float = COST_DEFAULTS['census']['p2']
    paths: int = 16
    use_gcp: bool = True
    theta: float = COST_DEFAULTS['census']['theta']
    c_hi: float = COST_DEFAULTS['census']['c_hi']
    c_low: float = COST_DEFAULTS['census']['c_low']
    # GCPs only where the right view's CNN disparity agrees (not in the paper).
    gcp_lr_check: bool = COST_DEFAULTS['census']['gcp_lr_check']
    weights: str = ''  # '' = the weights shipped with the package
    device: str = 'cpu'
    # bfloat16 CNN descriptors: True, False or 'auto' (where native: CPUs with avx512_bf16
    # or AMX, CUDA; see cnn.bf16_native). 3-4x faster CNN; on the validation frames the
    # defaults' error rates moved by at most 0.061 point (README, "Speed").
    bf16: bool | str = 'auto'
    subpixel: bool = True
    median: bool = False
    # Invalidation (stereo.postprocess; README "What is published"), chosen on the validation
    # frames; 0 / False turns each off. The left-right check is off: on the validation frames
    # 89 % of the pixels it rejects are right; its agreement is a confidence feature instead.
    valid_window: bool = True
    lr_check: bool = False
    uniqueness_ratio: float = 1.0  # percent, OpenCV's uniquenessRatio
    speckle_size: int = 100  # pixels, stereo_image_proc's speckle_size
    speckle_range: int = 4  # px, stereo_image_proc's speckle_range
    min_depth: float = 0.3  # metres, with a camera model; 0 = no limit
    max_depth: float = 0.0
    min_confidence: float = 0.88  # on the calibrated confidence of the disparity
    # Match at 1/downsample of the resolution (area-binned images, max_disp / downsample);
    # the outputs come back at full size, disparities in full-size pixels.
    downsample: int = 1
    # Pairs whose pipeline would need more memory are refused (see `memory_bytes`). 3 GiB:
    # with the process's own 0.4-0.6 GB the node stays under half of an 8 GB computer.
    memory_limit_mb: int = 3072

    @classmethod
    def for_cost(cls, cost, preset='default', **overrides):
        """Return a config with the `preset`'s values for `cost`, then `overrides` applied."""
        if preset not in PRESETS:
            raise ValueError(f'preset must be one of {tuple(PRESETS)}, got {preset!r}')
        if cost not in PRESETS[preset]:
            raise ValueError(f'cost must be one of {tuple(COST_DEFAULTS)}, got {cost!r}')
        return cls(**{'cost': cost, **PRESETS[preset][cost], **overrides}).validate()

    def replace(self, **changes):
        return dataclasses.replace(self, **changes).validate()

    def validate(self):
        """Return self, or raise ValueError saying which value is out of range and why."""
        cost_mod.check_window(self.cost, self.window)
        if not (isinstance(self.max_disp, (int, np.integer)) and 1 <= self.max_disp <= 1024):
            raise ValueError(f'max_disp must be an integer in [1, 1024], '
                             f'got {self.max_disp!r}')
        for name in ('p1', 'p2', 'theta', 'c_hi', 'c_low'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f'{name} must be a finite number >= 0, got {value!r}')
        if self.p2 < self.p1:
            raise ValueError(f'P2 ({self.p2}) must be >= P1 ({self.p1}): a disparity jump may not '
                             'cost less than a 1 px step')
        if self.paths not in PATHS:
            raise ValueError(f'paths must be one of {PATHS}, got {self.paths!r}')
        if self.theta > 1:
            raise ValueError('theta must be in [0, 1] (the CNN confidence range), '
                             f'got {self.theta}')
        if self.c_low > self.c_hi:
            raise ValueError(f'c_low ({self.c_low}) must be <= c_hi ({self.c_hi})')
        for name in ('uniqueness_ratio', 'speckle_range', 'min_depth', 'max_depth',
                     'min_confidence'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool)
                    and math.isfinite(value) and value >= 0):
                raise ValueError(f'{name} must be a finite number >= 0, got {value!r}')
        if self.uniqueness_ratio >= 100:
            raise ValueError('uniqueness_ratio must be below 100 (percent), '
                             f'got {self.uniqueness_ratio}')
        if not (isinstance(self.speckle_size, (int, np.integer))
                and not isinstance(self.speckle_size, bool) and self.speckle_size >= 0):
            raise ValueError(f'speckle_size must be an integer >= 0, got {self.speckle_size!r}')
        if self.max_depth and self.max_depth <= self.min_depth:
            raise ValueError(f'max_depth ({self.max_depth}) must be above min_depth '
                             f'({self.min_depth}), or 0 for no limit')
        if self.min_confidence > 1:
            raise ValueError('min_confidence must be in [0, 1] (a probability), '
                             f'got {self.min_confidence}')
        if not (isinstance(self.bf16, bool) or self.bf16 == 'auto'):  # 1 == True, but no
            raise ValueError(f"bf16 must be true, false or 'auto', got {self.bf16!r}")
        if not (self.device == 'cpu' or re.fullmatch(r'cuda(:\d+)?', self.device)):
            raise ValueError(f"device must be 'cpu' or 'cuda[:N]', got {self.device!r}")
        if not (isinstance(self.downsample, (int, np.integer)) and not isinstance(
                self.downsample, bool) and self.downsample in DOWNSAMPLE):
            raise ValueError(f'downsample must be one of {DOWNSAMPLE}, got {self.downsample!r}')
        if not (isinstance(self.memory_limit_mb, (int, np.integer))
                and not isinstance(self.memory_limit_mb, bool)
                and 64 <= self.memory_limit_mb <= 1 << 20):
            raise ValueError('memory_limit_mb must be an integer in [64, 1048576], '
                             f'got {self.memory_limit_mb!r}')
        return self

    @property
    def matched_disp(self):
        """Return the disparities searched at the matching resolution: max_disp / downsample."""
        return -(-self.max_disp // self.downsample)


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


def fixed_point_scale(cfg):
    """
    Return the smallest integer s that allows fixed-point uint16 volumes, or None.

    s makes s * (Census costs, P1, P2, and C_hi, C_low with GCPs) integers whose path sums,
    at most paths * s * (max cost + P2), fit in uint16 (s = 10 for the paper's C_low = 1.3);
    None for SAD, or values such as C_low = 1.2345, which would need s = 2000. With an s
    the pipeline keeps its volumes in uint16: half the memory, faster SGM, exact integer
    arithmetic; the disparities equal the float32 path's except where float32 rounding of a
    fractional value breaks a tie.
    """
    if cfg.cost != 'census':
        return None
    values = (cfg.p1, cfg.p2) + ((cfg.c_hi, cfg.c_low) if cfg.use_gcp else ())
    top = max(cost_mod.max_cost(cfg.cost, cfg.window), cfg.c_hi if cfg.use_gcp else 0)
    for s in range(1, int(cost_mod.UINT16_MAX // path_sum_bound(cfg.paths, top, cfg.p2)) + 1):
        if all(abs(v * s - round(v * s)) <= 1e-9 * max(1.0, v * s) for v in values):
            return s
    return None


def volume_arithmetic(cfg):
    """
    Return (scale, dtype, fixed) of the pipeline's volumes for `cfg`.

    `fixed_point_scale` (None for float32), the volume type (uint16 with a scale, else
    float32), and the map of a cost-unit parameter (P1, P2, C_hi, C_low) into the volume's.
    """
    scale = fixed_point_scale(cfg)
    if scale is None:
        return None, np.dtype(np.float32), lambda v: v
    return scale, np.dtype(np.uint16), lambda v: round(v * scale)


# Bytes per matched pixel besides the volumes, alive at once while the cost volume is built
# (the gray pair 8, the CNN outputs 12, the Census bit strings 48), rounded up; it covers
# the later stages too.
PIXEL_BYTES = 80
# While the CNN runs: the gray pair, its network input and the CNN outputs (8 + 8 + 12 bytes
# per pixel), and of one strip four layer outputs' worth (a convolution's, its ReLU's, the
# descriptors copied out, and oneDNN's scratchpad, which it keeps for the largest so far).
CNN_PIXEL_BYTES = 28
STRIP_LAYERS = 4
# With downsample > 1, per full-size pixel: the gray pair (8), the outputs blown up (17),
# rounded up.
FULL_PIXEL_BYTES = 32


def memory_bytes(cfg, height, width):
    """
    Return an upper bound of the memory the pipeline allocates for a pair of this size.

    At the matching resolution (H/downsample x W/downsample, D = matched_disp): the cost and
    path-sum volumes (H x W x D each, kept between frames) and the SGM sweep buffers (3 rows
    of each path from above, W x D each), plus whichever needs more: the CNN's arrays with
    one strip's activations (two images, 64 float32 maps of STRIP_ROWS + 8 rows), or
    PIXEL_BYTES per pixel for the later stages; with downsample, FULL_PIXEL_BYTES per
    full-size pixel. Measured peaks stay below it (README, "Failures, memory and shutdown").
    """
    fixed, per_disparity = _memory_terms(cfg, height, width)
    return fixed + per_disparity * cfg.matched_disp


def _memory_terms(cfg, height, width):
    """Return (bytes, bytes per matched disparity) of `memory_bytes`."""
    f = cfg.downsample
    h, w = height // f, width // f
    itemsize = volume_arithmetic(cfg)[1].itemsize
    sweep_rows = 3 * sum(dy > 0 for _, dy in directions(cfg.paths))
    per_disparity = (2 * h + sweep_rows) * w * itemsize
    fixed = PIXEL_BYTES * h * w
    if cfg.use_gcp:
        from .cnn import FEATURES, PAD, STRIP_ROWS
        strip = 2 * FEATURES * (min(STRIP_ROWS, h) + 2 * PAD) * (w + 2 * PAD) * 4
        fixed = max(fixed, CNN_PIXEL_BYTES * h * w + STRIP_LAYERS * strip)
    if f > 1:
        fixed += FULL_PIXEL_BYTES * height * width
    return fixed, per_disparity


def check_memory(cfg, height, width):
    """Raise ValueError if a pair of this size needs more than cfg.memory_limit_mb."""
    fixed, per_disparity = _memory_terms(cfg, height, width)
    need = fixed + per_disparity * cfg.matched_disp  # memory_bytes, from the same terms
    if need <= cfg.memory_limit_mb * MIB:
        return
    fits = (cfg.memory_limit_mb * MIB - fixed) // per_disparity * cfg.downsample
    f, nd = cfg.downsample, cfg.matched_disp
    changes = ([f'lower max_disparity (at most {fits} fits)'] if fits >= 1 else []) + (
        ['raise downsample'] if f < max(DOWNSAMPLE) else []) + ['raise memory_limit_mb']
    what = ', '.join(changes[:-1]) + ', or ' + changes[-1] if len(changes) > 1 else changes[0]
    raise ValueError(
        f'{width}x{height} at max_disparity {cfg.max_disp}'
        + (f', downsample {f},' if f > 1 else '')
        + f' needs about {need / MIB:.0f} MB (two {width // f}x{height // f}x{nd} '
        f'{volume_arithmetic(cfg)[1]} volumes), over memory_limit_mb {cfg.memory_limit_mb}: '
        + what)


# Blocks from this size on are mmap'd (`mmap_large_arrays`): above every block a KITTI-size
# frame allocates and frees while it runs (a CNN strip's layer output: 23 MB).
MMAP_BYTES = 64 * MIB


def _glibc(call, *args):
    """Call glibc's `call` (mallopt, malloc_trim); no-op without glibc."""
    try:
        getattr(ctypes.CDLL(None), call)(*args)
    except (OSError, AttributeError):
        pass


def mmap_large_arrays():
    """
    Make glibc's malloc serve blocks of MMAP_BYTES or more with mmap, in this whole process.

    For long-running processes (the node, the bag tool), with `StereoPipeline.release` at
    idle. By default glibc raises its mmap threshold up to 32 MiB after a large block is
    freed and serves blocks below it from heaps that keep freed memory: measured at 741x500,
    100 MB more after the arrays were let go and steady peaks 30 % higher. A fixed threshold
    of 1 MiB made RSS follow the arrays alive, but every block of a frame was then fresh
    pages (a page fault per 4 KiB): a KITTI pair took 1.3 s instead of 0.74 s (CNN 0.74 s
    instead of 0.35 s; README, "Speed"). With MMAP_BYTES the blocks freed within a pair (a
    CNN strip's layer outputs, 24 per pair) are reused within it, the volumes are mmap'd, and
    each pair ends by giving the freed heap memory back (malloc_trim), so RSS between pairs
    still follows the arrays alive.
    """
    _glibc('mallopt', -3, MMAP_BYTES)  # M_MMAP_THRESHOLD


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
        _glibc('malloc_trim', 0)  # kept arrays below MMAP_BYTES were heap blocks

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
        _glibc('malloc_trim', 0)  # the heap blocks this pair freed (see mmap_large_arrays)
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
