"""
StereoConfig: every setting of the pipeline, validated when made, and the presets.

`StereoConfig()` is the default configuration (Census + GCPs + SGM with the cross-validated
values and the invalidation of `postprocess`); `StereoConfig.for_cost(cost, preset)` takes a
cost's values from a preset ('default', or 'paper': the paper's values, nothing invalidated).
"""
import dataclasses
from dataclasses import dataclass
import math
import re

import numpy as np

from . import cost as cost_mod
from .sgm import PATHS

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
