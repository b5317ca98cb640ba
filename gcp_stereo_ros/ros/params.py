"""
The node's parameters, ROS-free: names, descriptions, ranges and their StereoConfig fields.

The node declares them; `gcp-stereo-bag run --params` reads the same YAML file, so a bag is
processed exactly as the live node would.
"""
from dataclasses import dataclass
from pathlib import Path

import yaml

from .sync import PairSync
from ..stereo.pipeline import COST_DEFAULTS, StereoConfig

NODE_NAME = 'gcp_stereo_node'


@dataclass(frozen=True)
class Param:
    name: str
    default: object
    description: str
    field: str | None = None  # StereoConfig field; None = node-only (sync, logging)
    # (low, high, step) for numbers; step 0 = continuous
    range: tuple | None = None  # noqa: A003 (read elsewhere as p.range, so keep the name)
    dynamic: bool = False  # takes values of more than one type (bf16: true, false or 'auto')


_D = StereoConfig()
PARAMS = (
    Param('cost', _D.cost,
          "matching cost: 'census' or 'sad' (a switch loads that cost's defaults for theta, "
          'P1, P2, c_hi, c_low unless set in the same atomic request)', 'cost'),
    Param('window', _D.window, 'matching window size in pixels (odd; census at most 11)',
          'window', (3, 31, 2)),
    Param('max_disparity', _D.max_disp, 'number of disparities searched: 0 .. max_disparity - 1',
          'max_disp', (1, 1024, 1)),
    Param('P1', _D.p1, 'SGM penalty for a 1 px disparity change', 'p1', (0.0, 10000.0, 0.0)),
    Param('P2', _D.p2, 'SGM penalty for larger disparity jumps (>= P1)',
          'p2', (0.0, 10000.0, 0.0)),
    Param('paths', _D.paths, 'SGM path directions: 4, 8 or 16', 'paths', (4, 16, 4)),
    Param('use_gcp', _D.use_gcp, 'refine the cost volume with CNN ground control points',
          'use_gcp'),
    Param('theta', _D.theta,
          'GCP threshold on the calibrated CNN confidence: the probability that the '
          "pixel's CNN disparity is within 1 px of the truth",
          'theta', (0.0, 1.0, 0.0)),
    Param('c_hi', _D.c_hi, 'cost given to every disparity of a non-GCP pixel',
          'c_hi', (0.0, 10000.0, 0.0)),
    Param('c_low', _D.c_low, 'cost given to a GCP at its CNN disparity (<= c_hi)',
          'c_low', (0.0, 10000.0, 0.0)),
    Param('gcp_lr_check', _D.gcp_lr_check,
          "GCPs only where the right view's CNN disparity agrees within 1 px", 'gcp_lr_check'),
    Param('weights', _D.weights,
          "CNN weights file ('' = the weights shipped with the package)", 'weights'),
    Param('device', _D.device,
          "'cpu', or 'cuda' / 'cuda:N' to run the whole pipeline on that GPU", 'device'),
    Param('bf16', _D.bf16, "bfloat16 CNN descriptors: true, false or 'auto' (on where native: "
          'CPUs with avx512_bf16 or AMX, CUDA)', 'bf16', dynamic=True),
    Param('subpixel', _D.subpixel, 'parabola fit for sub-pixel disparities', 'subpixel'),
    Param('lr_check', _D.lr_check,
          'left-right consistency check (invalid pixels published as -1)', 'lr_check'),
    Param('median', _D.median, '3x3 median filter on the disparity', 'median'),
    Param('downsample', _D.downsample,
          'match at 1/N resolution (1, 2 or 4): both images area-binned, max_disparity / N; '
          'outputs at full size, disparities in full-size pixels', 'downsample', (1, 4, 1)),
    Param('approximate_sync', False,
          'pair left/right images whose stamps differ by at most the tolerance'),
    Param('approximate_sync_tolerance_seconds', 0.0,
          'largest stamp difference of an approximate pair', range=(0.0, 10.0, 0.0)),
    Param('queue_size', 5, 'images kept per side while waiting for the twin', range=(1, 1000, 1)),
    Param('log_every_n_frames', 30,
          'log stage timings, input rate and drops every N frames (0 = never)',
          range=(0, 100000, 1)),
)
BY_NAME = {p.name: p for p in PARAMS}
COST_PARAMS = {'theta': 'theta', 'P1': 'p1', 'P2': 'p2', 'c_hi': 'c_hi', 'c_low': 'c_low'}
SYNC_PARAMS = ('queue_size', 'approximate_sync', 'approximate_sync_tolerance_seconds')


def cost_defaults(cost):
    """ROS-named defaults that follow the matching cost."""
    if cost not in COST_DEFAULTS:
        raise ValueError(f"cost must be 'census' or 'sad', got {cost!r}")
    return {name: COST_DEFAULTS[cost][field] for name, field in COST_PARAMS.items()}


def config_from_params(values):
    """
    Build the StereoConfig from ROS-named parameter values.

    Cost-dependent ones that are missing take the chosen cost's defaults. Raises ValueError
    for unknown names or invalid values.
    """
    unknown = set(values) - set(BY_NAME)
    if unknown:
        raise ValueError(f'unknown parameter(s) {sorted(unknown)}; known: {sorted(BY_NAME)}')
    fields = {BY_NAME[n].field: v for n, v in values.items() if BY_NAME[n].field and n != 'cost'}
    return StereoConfig.for_cost(values.get('cost', _D.cost), **fields)


def make_sync(values):
    """Build the PairSync that ROS-named parameter values ask for (defaults for missing ones)."""
    return PairSync(*(values.get(name, BY_NAME[name].default) for name in SYNC_PARAMS))


def load_params_file(path):
    """
    Return the parameter values from a ROS params YAML.

    The file has the form `<node or /**>: ros__parameters: {...}`; `qos_overrides`, which
    only rclpy reads, is left out.
    """
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ValueError(f'cannot read parameters file {path}: {err}') from err
    for key in (NODE_NAME, '/' + NODE_NAME, '/**'):
        if (isinstance(doc, dict) and isinstance(doc.get(key), dict)
                and 'ros__parameters' in doc[key]):
            values = dict(doc[key]['ros__parameters'])
            values.pop('qos_overrides', None)  # rclpy's QoS settings, not pipeline parameters
            return values
    raise ValueError(f'{path}: expected "{NODE_NAME}:" or "/**:" with "ros__parameters:" inside')
