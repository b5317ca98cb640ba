"""
StereoConfig: every setting of the pipeline, validated when made, and the presets.

`StereoConfig()` is the default configuration (Census + GCPs + SGM with the cross-validated
values and the invalidation of `postprocess`); `StereoConfig.for_cost(cost, preset)` takes a
cost's values from a preset ('default', or 'paper': the paper's values, nothing invalidated).
"""
import dataclasses
from dataclasses import dataclass
import re
from typing import Any, Collection

import numpy as np

from .cost import check_window
from .costs import cost_spec, COSTS
from .sgm import PATHS

# Every invalidation off (stereo.postprocess). The paper published every integer WTA
# disparity: its preset has this and no sub-pixel fit.
UNFILTERED: dict[str, Any] = {
    'valid_window': False, 'lr_check': False, 'plain_check': 0.0, 'uniqueness_ratio': 0.0,
    'speckle_size': 0, 'min_depth': 0.0, 'max_depth': 0.0, 'min_confidence': 0.0,
    'background_ratio': 0.0}
# What each preset sets besides a cost's own values (`costs.CostSpec.presets`).
PRESETS: dict[str, dict[str, Any]] = {
    'default': {},
    'paper': {**UNFILTERED, 'subpixel': False, 'cnn_filter_radius': 0, 'align': False},
    # Rate on a CPU: matching at half resolution, 4 SGM paths, no alignment (doc/speed.md,
    # "The real-time preset": each lever measured).
    'realtime': {'downsample': 2, 'paths': 4, 'align': False},
}
DOWNSAMPLE = (1, 2, 4)
PRECISIONS = ('auto', 'int8', 'bf16', 'fp32')
MAX_COST_PARAM = 10000.0  # P1, P2, c_hi, c_low: far above any useful value of either cost
# The valid values of each number field, both ends included: the one source of truth,
# which the node's parameter descriptors are made from (ros/params.py). The window's
# range depends on the cost (`CostSpec.windows`).
RANGES: dict[str, tuple[int, int] | tuple[float, float]] = {
    'max_disp': (1, 1024),
    'p1': (0.0, MAX_COST_PARAM),
    'p2': (0.0, MAX_COST_PARAM),
    'theta': (0.0, 1.0),
    'cnn_filter_radius': (0, 8),
    'c_hi': (0.0, MAX_COST_PARAM),
    'c_low': (0.0, MAX_COST_PARAM),
    'plain_check': (0.0, 1024.0),
    'uniqueness_ratio': (0.0, 99.0),
    'speckle_size': (0, 1_000_000),
    'speckle_range': (0, 1024),
    'min_depth': (0.0, 1e6),
    'max_depth': (0.0, 1e6),
    'min_confidence': (0.0, 1.0),
    'background_ratio': (0.0, 100.0),
    'memory_limit_mb': (64, 1 << 20),
}
# The only values of these fields (the costs: those registered, `costs.COSTS`).
CHOICES: dict[str, Collection[Any]] = {'cost': COSTS.keys(), 'paths': PATHS,
                                       'downsample': DOWNSAMPLE, 'precision': PRECISIONS}
# The fields the CNN's outputs (StereoResult cof_c, cof_d, cof_dr) depend on: a run may reuse
# another's outputs (`StereoPipeline.__call__`'s `cnn`) only where these are the same.
CNN_FIELDS = ('weights', 'device', 'precision', 'max_disp', 'downsample', 'cnn_filter_radius',
              'align')
FLAGS = ('use_gcp', 'gcp_lr_check', 'gcp_plain_check', 'subpixel', 'median', 'valid_window',
         'lr_check', 'align')
DEVICE = re.compile(r'cpu|cuda(:\d+)?')
_CENSUS = COSTS['census'].presets['default']  # the default cost's values


def number_text(value: float) -> str:
    """Return `value` as the range messages and the docs write it: 1e6 as 1000000."""
    return str(int(value)) if float(value).is_integer() else f'{value:g}'


def range_text(low: float, high: float) -> str:
    """Return the inclusive range [low, high] as text, e.g. '[0, 10000]'."""
    return f'[{number_text(low)}, {number_text(high)}]'


@dataclass(frozen=True)
class StereoConfig:
    """
    Every setting of the stereo pipeline, checked when the config is made.

    Make one with keywords (``StereoConfig(max_disp=64, paths=8)``), from a preset
    (`for_cost`) or from another (`replace`); a value out of its range raises ValueError
    naming every bad field, its range and the value given. Costs are in the matching cost's
    units: differing bits for Census (0 .. window**2 - 1), image standard deviations for SAD
    (0 .. 3.2). Sizes and disparities are in px of the input images, also with
    ``downsample``. The node's parameters map onto these fields (doc/parameters.md); what
    each does and how its default was chosen: doc/method.md, doc/published.md.

    Attributes
    ----------
    cost : str
        Matching cost, a registered one (`costs.COSTS`): ``'census'`` or ``'sad'``;
        default 'census'.
    window : int
        Matching window side, px, odd: census in [3, 11], sad in [3, 31]; default 9.
    max_disp : int
        Disparities searched, 0 .. max_disp - 1 px; in [1, 1024], default 128.
    p1 : float
        SGM penalty of a 1 px disparity step, cost units; in [0, 10000]: census 12, sad 0.02.
    p2 : float
        SGM penalty of a larger jump, cost units; in [0, 10000], >= p1: census 128, sad 0.5.
    paths : int
        SGM path directions: 4, 8 or 16; default 16.
    use_gcp : bool
        Refine the cost volume with the CNN's ground control points (GCPs); default True.
    theta : float
        GCP threshold on the calibrated CNN confidence, P(CNN disparity within 1 px);
        in [0, 1], default 0.2.
    c_hi : float
        Cost of every disparity of a non-GCP pixel, cost units; in [0, 10000]: census 200,
        sad 5.
    c_low : float
        Cost of a GCP at its CNN disparity, cost units; in [0, 10000], <= c_hi: census 2,
        sad 0.001.
    gcp_lr_check : bool
        GCPs only where the right view's CNN disparity agrees within 1 px; default True.
    gcp_plain_check : bool
        GCPs only where the CNN disparity is at most 1 px above plain SGM's (the same
        costs without GCPs); census True, sad False.
    cnn_filter_radius : int
        Guided filter of the CNN confidence volume, px (windows of 2 r + 1); in [0, 8],
        0 = off, default 4.
    weights : str
        CNN weights file, ``''`` for the weights shipped with the package; default ''.
    device : str
        ``'cpu'``, or ``'cuda'`` / ``'cuda:N'``: the whole pipeline on that GPU; default 'cpu'.
    precision : str
        Arithmetic of the CNN's convolutions: ``'int8'`` (CPU only), ``'bf16'``, ``'fp32'``,
        or ``'auto'``: the fastest native one (`cnn.resolve_precision`); default 'auto'.
    subpixel : bool
        Parabola fit of the summed costs for sub-pixel disparities; default True.
    median : bool
        3x3 median filter on the disparity; default False.
    valid_window : bool
        Invalidate where the search was cut short (image edge, left band); default True.
    lr_check : bool
        Invalidate where the right view's winner is more than 1 px off; default False.
    plain_check : float
        With GCPs, invalidate where the disparity is more than this above plain SGM's, px;
        in [0, 1024], 0 = off: census 1.5, sad 0.
    uniqueness_ratio : float
        OpenCV's uniquenessRatio on the summed SGM costs, percent; in [0, 99], 0 = off,
        default 1.
    speckle_size : int
        Invalidate connected regions of at most this many px; in [0, 1000000], 0 = off,
        default 100.
    speckle_range : int
        Largest disparity difference of two neighbours in one speckle region, px;
        in [0, 1024], default 4.
    min_depth : float
        Invalidate depths below this, m (with a camera model); in [0, 1000000], 0 = no
        limit, default 0.3.
    max_depth : float
        Invalidate depths beyond this, m (with a camera model); in [0, 1000000], above
        min_depth or 0 = no limit; default 0.
    min_confidence : float
        Invalidate where the disparity confidence, P(within 3 px), is below this and the
        pixel's background fits; in [0, 1], 0 = off, default 0.9.
    background_ratio : float
        A pixel below min_confidence goes only where its row's background has a summed SGM
        cost at most this times the winner's; in [0, 100], 0 = off, else >= 1; default 1.1.
    downsample : int
        Match at 1 / downsample of the resolution: 1, 2 or 4; default 1.
    memory_limit_mb : int
        A pair that would need more memory is refused, MiB; in [64, 1048576], default 3072.
    align : bool
        Measure the pair's vertical misalignment and undo it where the data supports it
        and it reaches 0.25 px (`alignment`; doc/alignment.md); False: take the pair as it
        is (the paper and realtime presets); default True.

    """

    cost: str = 'census'
    window: int = 9
    max_disp: int = 128
    p1: float = _CENSUS['p1']
    p2: float = _CENSUS['p2']
    paths: int = 16
    use_gcp: bool = True
    theta: float = _CENSUS['theta']
    c_hi: float = _CENSUS['c_hi']
    c_low: float = _CENSUS['c_low']
    gcp_lr_check: bool = _CENSUS['gcp_lr_check']
    gcp_plain_check: bool = _CENSUS['gcp_plain_check']
    cnn_filter_radius: int = 4
    weights: str = ''
    device: str = 'cpu'
    precision: str = 'auto'
    subpixel: bool = True
    median: bool = False
    # Invalidation (stereo.postprocess), chosen on the validation frames (doc/published.md;
    # why the left-right check is off: "The left-right check is off by default" there).
    valid_window: bool = True
    lr_check: bool = False
    plain_check: float = _CENSUS['plain_check']
    uniqueness_ratio: float = 1.0
    speckle_size: int = 100
    speckle_range: int = 4
    min_depth: float = 0.3
    max_depth: float = 0.0
    min_confidence: float = 0.9
    background_ratio: float = 1.1
    downsample: int = 1
    memory_limit_mb: int = 3072
    align: bool = True

    def __post_init__(self) -> None:
        """Raise ValueError naming every field whose value is invalid (see `_problems`)."""
        found = self._problems()
        if found:
            raise ValueError('; '.join(found))

    @classmethod
    def for_cost(cls, cost: str, preset: str = 'default', **overrides: Any) -> 'StereoConfig':
        """
        Return the config with the `preset`'s values for `cost`, then `overrides` applied.

        `preset` is ``'default'`` (cross-validated on the validation frames),
        ``'paper'`` (Zhong et al.'s values, nothing invalidated, no sub-pixel fit) or
        ``'realtime'`` (camera rate on a CPU, for the costs that have its values): the
        cost's default values, then its values of the preset (`CostSpec.presets`), then
        the preset's own (`PRESETS`); `overrides` are fields. Raises ValueError for an
        unknown preset or cost, a preset the cost has no values of, or an invalid value.
        """
        if preset not in PRESETS:
            raise ValueError(f'preset must be one of {tuple(PRESETS)}, got {preset!r}')
        spec = cost_spec(cost)
        if preset not in spec.presets:
            raise ValueError(f'preset {preset!r} has no values for cost {cost!r} (it has: '
                             f'{", ".join(spec.presets)})')
        return cls(**{'cost': cost, **spec.presets['default'], **spec.presets.get(preset, {}),
                      **PRESETS[preset], **overrides})

    def replace(self, **changes: Any) -> 'StereoConfig':
        """Return a copy with the fields `changes` changed (``dataclasses.replace``)."""
        return dataclasses.replace(self, **changes)

    def _problems(self) -> list[str]:
        """
        Return a sentence for each invalid value, [] if all are valid.

        Each names the field, what it must be (its range from RANGES, its choices) and the
        value given; relations between fields (p1 <= p2, c_low <= c_hi, min_depth <
        max_depth) are checked once both values are valid on their own.
        """
        found = []
        for name, choices in CHOICES.items():
            value = getattr(self, name)
            if not any(_same(value, c) for c in choices):
                found.append(f'{name} must be one of {", ".join(map(repr, choices))}, '
                             f'got {value!r}')
        if self.cost in COSTS:
            try:
                check_window(self.cost, self.window)
            except ValueError as err:
                found.append(str(err))
        for name, (low, high) in RANGES.items():
            value = getattr(self, name)
            kind = 'an integer' if isinstance(low, int) else 'a number'
            if not (_is_number(value, isinstance(low, int)) and low <= value <= high):
                found.append(f'{name} must be {kind} in {range_text(low, high)}, got {value!r}')
        for name in FLAGS:
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                found.append(f'{name} must be true or false, got {getattr(self, name)!r}')
        if not isinstance(self.weights, str):
            found.append(f"weights must be a file path ('' = the shipped weights), "
                         f'got {self.weights!r}')
        if not (isinstance(self.device, str) and DEVICE.fullmatch(self.device)):
            found.append(f"device must be 'cpu' or 'cuda[:N]', got {self.device!r}")
        elif self.device != 'cpu' and self.cost in COSTS and cost_spec(self.cost).cuda is None:
            found.append(f"cost {self.cost!r} has no CUDA kernel: use device 'cpu'")
        elif self.precision == 'int8' and self.device != 'cpu':
            found.append(f"precision 'int8' runs on the CPU only, not on {self.device}: use "
                         "'auto', 'bf16' or 'fp32' there")
        bad = {text.split(' ', 1)[0] for text in found}
        if not {'p1', 'p2'} & bad and self.p2 < self.p1:
            found.append(f'P2 ({self.p2}) must be >= P1 ({self.p1}): a disparity jump may not '
                         'cost less than a 1 px step')
        if not {'c_hi', 'c_low'} & bad and self.c_low > self.c_hi:
            found.append(f'c_low ({self.c_low}) must be <= c_hi ({self.c_hi})')
        if 'background_ratio' not in bad and 0 < self.background_ratio < 1:
            found.append(f'background_ratio must be 0 (off) or at least 1 (a cost ratio to '
                         f'the winner, whose cost is the least), got {self.background_ratio!r}')
        if (not {'min_depth', 'max_depth'} & bad and self.max_depth
                and self.max_depth <= self.min_depth):
            found.append(f'max_depth ({self.max_depth}) must be above min_depth '
                         f'({self.min_depth}), or 0 for no limit')
        return found

    @property
    def matched_radius(self) -> int:
        """Return the CNN filter's radius on the matching grid: r / downsample, >= 1 (0: off)."""
        return max(1, self.cnn_filter_radius // self.downsample) if self.cnn_filter_radius else 0

    @property
    def plain_sgm(self) -> bool:
        """Whether plain SGM runs: with GCPs, for gcp_plain_check or plain_check."""
        return self.use_gcp and bool(self.gcp_plain_check or self.plain_check)

    @property
    def matched_disp(self) -> int:
        """Return the disparities searched at the matching resolution: max_disp / downsample."""
        return -(-self.max_disp // self.downsample)


def _is_number(value: object, integer: bool) -> bool:
    """Whether `value` is a finite number (an integer if `integer`); booleans are not."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, (int, np.integer)):
        return True
    return not integer and isinstance(value, (float, np.floating)) and bool(np.isfinite(value))


def _same(value: object, choice: object) -> bool:
    """Whether `value` is `choice`, and of its kind: True is not 1, 2.0 is not 2."""
    flag = isinstance(value, (bool, np.bool_))
    if flag or isinstance(choice, bool):
        return flag and isinstance(choice, bool) and bool(value) == choice
    if isinstance(choice, int):
        return isinstance(value, (int, np.integer)) and value == choice
    return isinstance(value, str) and value == choice
