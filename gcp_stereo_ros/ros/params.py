"""
The node's parameters, ROS-free: names, descriptions, ranges and their StereoConfig fields.

The node declares them; `gcp-stereo-bag run --params` reads the same YAML file (a shipped
config, or what `ros2 param dump` wrote), so a bag is processed exactly as the live node would.

Each registered matching cost (`stereo.costs.COSTS`) has its own window, theta, P1, P2, c_hi,
c_low, gcp_plain_check and plain_check (`census.P2`, ...), with the cost's default values:
switching `cost` changes no other parameter, so parameters
can be set in any order (as `ros2 param load` does, alphabetically) and `ros2 param dump`
then `load` restores exactly what was dumped.
"""
from dataclasses import dataclass
import difflib
from pathlib import Path

import yaml

from ..stereo.alignment import MAX_CORRECTION, MIN_CORRECTION
from ..stereo.config import CHOICES, range_text, RANGES, StereoConfig
from ..stereo.costs import cost_spec, COSTS
from ..stereo.drift import BUDGET, ERROR, WARN

NODE_NAME = 'gcp_stereo_node'
# Parameters every rclpy node declares (a dump holds them); the bag tools leave them out.
RCLPY_PARAMS = ('use_sim_time', 'start_type_description_service')


@dataclass(frozen=True)
class Param:
    """
    One node parameter: its name, default, description and StereoConfig field.

    A field's parameter takes its range or choices from the config (config.RANGES,
    config.CHOICES, `CostSpec.windows`), so the node's descriptors and the config's checks
    are one: only node-only parameters give their own.
    """

    name: str
    default: object
    description: str
    field: str | None = None  # StereoConfig field; None = node-only (input, sync, outputs)
    # (low, high, step) for numbers; step 0 = continuous
    range: tuple | None = None  # noqa: A003 (read elsewhere as p.range, so keep the name)
    choices: tuple | None = None  # the only values allowed (said in the descriptor)
    cost: str | None = None  # the matching cost this value belongs to (None = any)

    def __post_init__(self):
        """Take the field's range or choices from the config, unless given."""
        if self.field == 'window':
            object.__setattr__(self, 'range', (*cost_spec(self.cost).windows, 2))
        elif self.field in RANGES:
            low, high = RANGES[self.field]
            object.__setattr__(self, 'range', (low, high, 1 if isinstance(low, int) else 0.0))
        elif self.field in CHOICES and self.choices is None:
            object.__setattr__(self, 'choices', tuple(CHOICES[self.field]))


def _cost_params(cost):
    """Return the parameters of the registered cost `cost`, with its default values."""
    d = cost_spec(cost).presets['default']
    return (
        Param(f'{cost}.window', _D.window, f'{cost}: matching window size in pixels (odd)',
              'window', cost=cost),
        Param(f'{cost}.theta', d['theta'], f'{cost}: GCP threshold on the calibrated CNN '
              "confidence: the probability that the pixel's CNN disparity is within 1 px of "
              'the truth', 'theta', cost=cost),
        Param(f'{cost}.P1', d['p1'], f'{cost}: SGM penalty for a 1 px disparity change',
              'p1', cost=cost),
        Param(f'{cost}.P2', d['p2'], f'{cost}: SGM penalty for larger disparity jumps (>= P1)',
              'p2', cost=cost),
        Param(f'{cost}.c_hi', d['c_hi'], f'{cost}: cost given to every disparity of a non-GCP '
              'pixel', 'c_hi', cost=cost),
        Param(f'{cost}.c_low', d['c_low'], f'{cost}: cost given to a GCP at its CNN disparity '
              '(<= c_hi)', 'c_low', cost=cost),
        Param(f'{cost}.gcp_plain_check', d['gcp_plain_check'], f'{cost}: GCPs only where the '
              'CNN disparity is at most 1 px above the one SGM finds on the same costs '
              'without the GCPs', 'gcp_plain_check', cost=cost),
        Param(f'{cost}.plain_check', d['plain_check'], f'{cost}: invalidate where the '
              'disparity is more than this many px above the one SGM finds on the same costs '
              'without the GCPs (a second opinion without the CNN; 0 = off)', 'plain_check',
              cost=cost),
    )


_D = StereoConfig()
PARAMS = (
    Param('cost', _D.cost,
          'matching cost: ' + '; '.join(f"'{s.name}' ({s.summary})" for s in COSTS.values())
          + '; each has its own window, theta, P1, P2, c_hi, c_low, gcp_plain_check, '
          f'plain_check ({", ".join(f"{c}.*" for c in COSTS)}), which a switch leaves as '
          'they are', 'cost'),
    Param('max_disparity', _D.max_disp, 'number of disparities searched: 0 .. max_disparity - 1',
          'max_disp'),
    *(p for cost in COSTS for p in _cost_params(cost)),
    Param('paths', _D.paths, 'SGM path directions: 4, 8 or 16', 'paths'),
    Param('use_gcp', _D.use_gcp, 'refine the cost volume with CNN ground control points',
          'use_gcp'),
    Param('gcp_lr_check', _D.gcp_lr_check,
          "GCPs only where the right view's CNN disparity agrees within 1 px", 'gcp_lr_check'),
    Param('cnn_filter_radius', _D.cnn_filter_radius,
          'guided filter of the CNN confidence volume before the GCPs are taken from it, '
          'windows of 2 r + 1 px (r / downsample, at least 1, on the matching grid), the '
          'left image as the guide (0 = off)', 'cnn_filter_radius'),
    Param('weights', _D.weights,
          "CNN weights file ('' = the weights shipped with the package)", 'weights'),
    Param('device', _D.device,
          "'cpu', or 'cuda' / 'cuda:N' to run the whole pipeline on that GPU", 'device'),
    Param('precision', _D.precision,
          "arithmetic of the CNN's convolutions: 'int8' (CPU only), 'bf16', 'fp32', or 'auto' "
          '(int8 on CPUs with AVX512-VNNI, AVX-VNNI or AMX, else bf16 where native: '
          'avx512_bf16, AMX, CUDA; else fp32)', 'precision'),
    Param('subpixel', _D.subpixel, 'parabola fit for sub-pixel disparities', 'subpixel'),
    Param('median', _D.median, '3x3 median filter on the disparity', 'median'),
    # Invalidation (stereo.postprocess): invalid pixels are published as min_disparity - 1,
    # NaN in depth and points2.
    Param('valid_window', _D.valid_window,
          'invalidate where the search was cut short: within window / 2 of the image edge, '
          'and left of x = max_disparity - 1 (fewer candidates) where the winner is at the '
          'end of its range', 'valid_window'),
    Param('lr_check', _D.lr_check, "invalidate where the right view's winner is more than "
          '1 px from the disparity (left-right check)', 'lr_check'),
    Param('uniqueness_ratio', _D.uniqueness_ratio,
          'invalidate where a disparity more than 1 px from the winner has a summed SGM cost '
          "less than this many percent above the winner's (OpenCV's uniquenessRatio; 0 = off)",
          'uniqueness_ratio'),
    Param('speckle_size', _D.speckle_size,
          'invalidate regions of at most this many pixels, neighbours within speckle_range '
          '(as stereo_image_proc; 0 = off)', 'speckle_size'),
    Param('speckle_range', _D.speckle_range, 'largest disparity difference in px of two '
          'neighbours of one speckle region', 'speckle_range'),
    Param('min_depth', _D.min_depth, 'invalidate depths below this many metres (with '
          'camera_info; 0 = no limit)', 'min_depth'),
    Param('max_depth', _D.max_depth, 'invalidate depths beyond this many metres (with '
          'camera_info; 0 = no limit)', 'max_depth'),
    Param('min_confidence', _D.min_confidence,
          'invalidate where disparity_confidence, the calibrated probability that the '
          'disparity is within 3 px of the truth, is below this (0 = off), where the '
          "pixel's background fits (background_ratio)", 'min_confidence'),
    Param('background_ratio', _D.background_ratio,
          'a pixel below min_confidence goes only where the summed SGM cost of its '
          'background (the smaller disparity of the nearest pixels left and right in its row '
          "that stay) is at most this many times the winner's (0 = off: every such pixel "
          'goes; else at least 1)', 'background_ratio'),
    Param('downsample', _D.downsample,
          'match at 1/N resolution (1, 2 or 4): both images area-binned, max_disparity / N; '
          'outputs at full size, disparities in full-size pixels', 'downsample'),
    Param('memory_limit_mb', _D.memory_limit_mb,
          'memory budget in MiB of processing one pair: a pair that would need more is '
          'refused, saying what to lower', 'memory_limit_mb'),
    Param('align', _D.align,
          "measure the right view's vertical misalignment (a drifting rig) every few frames, "
          'smooth it over them and undo it where the data supports it and it reaches 0.25 px; '
          '/diagnostics reports it (doc/alignment.md). false: take the pair as it is',
          'align'),
    Param('align_warn_px', WARN, '/diagnostics turns WARN (the rig has drifted, recalibrate) '
          'from a misalignment of this many px', range=(0.0, 100.0, 0.0)),
    Param('align_error_px', ERROR, '/diagnostics turns ERROR beyond a misalignment of this '
          'many px, and the node no longer corrects it (too large to correct: recalibrate)',
          range=(MIN_CORRECTION, MAX_CORRECTION, 0.0)),
    Param('align_budget', BUDGET, "the misalignment's estimates and corrections take at most "
          "this share of the frames' time", range=(0.0, 1.0, 0.0)),
    Param('image_transport', 'raw',
          "input images: 'raw' (sensor_msgs/Image) or 'compressed' (sensor_msgs/"
          'CompressedImage, jpeg or png, on <image topic>/compressed)',
          choices=('raw', 'compressed')),
    Param('rectify', False,
          'subscribe left/image_raw, right/image_raw and rectify them with the camera_info '
          'K, D, R, P (false: left/image_rect, right/image_rect are rectified already)'),
    Param('approximate_sync', False,
          'pair left/right images whose stamps differ by at most the tolerance (the closest '
          'stamps with a tolerance of 0)'),
    Param('approximate_sync_tolerance_seconds', 0.0,
          'largest stamp difference of an approximate pair (0: the closest stamps, as '
          "message_filters' ApproximateTime)", range=(0.0, 10.0, 0.0)),
    Param('queue_size', 5, 'images kept per side while waiting for the twin (at most '
          'memory_limit_mb / 4 of them in bytes)', range=(1, 1000, 1)),
    Param('use_color', True, "points2 carries the left image's colour in an rgb field"),
    Param('avoid_point_cloud_padding', False,
          'points2 without alignment padding: 16 bytes a point with rgb, 12 without '
          '(padded: 32 and 16)'),
    Param('log_every_n_frames', 30,
          'log stage timings, input rate and drops every N frames (0 = never)',
          range=(0, 100000, 1)),
)
BY_NAME = {p.name: p for p in PARAMS}
ORDERED = (('P1', 'P2'), ('c_low', 'c_hi'))  # (low, high): low <= high within each cost
SYNC_PARAMS = ('queue_size', 'approximate_sync', 'approximate_sync_tolerance_seconds',
               'memory_limit_mb')
INPUT_PARAMS = ('image_transport', 'rectify')
# Parameters of earlier releases: what each became.
RENAMED = {'bf16': "precision ('bf16' for bf16 true, 'fp32' for false, 'auto' for auto)"}


def check_names(names, where=''):
    """Raise ValueError naming the parameters in `names` the node does not have."""
    unknown = sorted(set(names) - set(BY_NAME))
    if unknown:
        per_cost = sorted({n for n in unknown if f'{_D.cost}.{n}' in BY_NAME})
        hint = (f' ({", ".join(per_cost)}: each cost has its own, e.g. '
                + ', '.join(f'{c}.{per_cost[0]}' for c in COSTS) + ')' if per_cost else '')
        hint += ''.join(f' ({n} is now {RENAMED[n]})' for n in unknown if n in RENAMED)
        raise ValueError(f'{where}unknown parameter(s) {unknown}{hint}{_guesses(unknown)}; '
                         f'known: {sorted(BY_NAME)}')


def _guesses(names):
    """Return ' (did you mean ...?)' with the known names close to unknown `names`, or ''."""
    short = {n.split('.', 1)[1]: n for n in BY_NAME if n.startswith(f'{_D.cost}.')}
    guesses = {}
    for name in names:
        close = difflib.get_close_matches(name, [*BY_NAME, *short], n=1)
        if close and close[0] != name:
            guesses[name] = short.get(close[0], close[0])
    if not guesses:
        return ''
    if len(names) == 1:
        return f' (did you mean {guesses[names[0]]!r}?)'
    return ' (did you mean ' + ', '.join(f'{g!r} for {n!r}' for n, g in guesses.items()) + '?)'


def coerce(name, value):
    """
    Return `value` as parameter `name` takes it: a whole number for a decimal one as float.

    YAML `P1: 4`, `-p census.P1:=300` and `ros2 param set ... census.P1 300` give integers.
    Raises ValueError for a value of the wrong type, not among the parameter's choices or
    outside its range (what the node's descriptor allows).
    """
    p = BY_NAME[name]
    if isinstance(p.default, float) and type(value) is int:
        value = float(value)
    if type(value) is not type(p.default):
        raise ValueError(f'{name} takes a {type(p.default).__name__} value, got {value!r}')
    if p.choices and value not in p.choices:
        raise ValueError(f'{name} must be one of {", ".join(map(repr, p.choices))}, '
                         f'got {value!r}')
    if p.range is not None:
        low, high, step = p.range
        if not (low <= value <= high and (step <= 1 or (value - low) % step == 0)):
            steps = f' in steps of {step} from {low}' if step > 1 else ''
            raise ValueError(f'{name} must be in {range_text(low, high)}{steps}, got {value!r}')
    return value


def config_from_params(values):
    """
    Build the StereoConfig of the chosen `cost` from ROS-named parameter values.

    Missing values take their defaults. Both costs' values are checked, so that switching
    `cost` can never fail. Raises ValueError for unknown names or invalid values.
    """
    check_names(values)
    values = {n: coerce(n, v) for n, v in values.items()}
    # The values of neither cost first, so that their errors are not said of a cost.
    StereoConfig(**{BY_NAME[n].field: v for n, v in values.items()
                    if BY_NAME[n].field and n != 'cost' and BY_NAME[n].cost is None})
    configs = {}
    for cost in COSTS:
        fields = {BY_NAME[n].field: v for n, v in values.items()
                  if BY_NAME[n].field and n != 'cost' and BY_NAME[n].cost in (None, cost)}
        try:
            configs[cost] = StereoConfig.for_cost(cost, **fields)
        except ValueError as err:
            raise ValueError(f'{cost}: {err}') from None
    return configs[values.get('cost', _D.cost)]


def _crossed(values):
    """Yield (cost, low name, high name, low value, high value) of each pair that crosses."""
    for cost in COSTS:
        for low, high in ORDERED:
            a, b = (values.get(f'{cost}.{n}', BY_NAME[f'{cost}.{n}'].default) for n in (low, high))
            if a > b:
                yield cost, low, high, a, b


def inconsistencies(values):
    """
    Return the reasons why `values` break P1 <= P2 or c_low <= c_hi within a cost.

    The node takes such values one at a time (`ros2 param load` sets P1 before P2), so a
    pair may cross for a while; an empty list when none does.
    """
    return [f'{cost}: {high} ({b}) must be >= {low} ({a})'
            for cost, low, high, a, b in _crossed(values)]


def uncrossed(values):
    """Return `values` with each crossed pair's high value raised to the low one."""
    return {**values, **{f'{cost}.{high}': a for cost, _, high, a, _ in _crossed(values)}}


def read_yaml(path):
    """Return the parsed YAML file at `path`; ValueError in one line if it cannot be read."""
    try:
        return yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ValueError(f'cannot read parameters file {path}: '
                         + ' '.join(str(err).split())) from err


def check_params_files(argv):
    """Raise ValueError if a `--params-file` among command-line arguments cannot be read."""
    for flag, path in zip(argv, argv[1:]):
        if flag == '--params-file':
            read_yaml(path)


def _flatten(params, prefix=''):
    """Flatten nested parameter dicts into dotted names, as rclpy reads a params file."""
    flat = {}
    for key, value in params.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f'{prefix}{key}.'))
        else:
            flat[f'{prefix}{key}'] = value
    return flat


def load_params_file(path):
    """
    Return the parameter values a ROS params YAML gives the node.

    The entries are those keyed `/**` (or any wildcard) and those for the node in any
    namespace (`gcp_stereo_node`, `/ns/gcp_stereo_node`, `/**/gcp_stereo_node`), wildcards
    first, merged in that order as rcl does; a file with a single entry (what `ros2 param
    dump` writes, for any node name) is taken whatever its key. Nested names are flattened
    (`census: {P1: 4}` -> `census.P1`); rclpy's own parameters (`use_sim_time`,
    `start_type_description_service`, `qos_overrides`) are left out, and whole numbers for
    decimal parameters become floats. Raises ValueError for an unreadable file, no entry for
    the node, unknown parameters or values of the wrong type.
    """
    path = Path(path)
    doc = read_yaml(path)
    entries = {key: body['ros__parameters'] for key, body in (doc or {}).items()
               if isinstance(body, dict) and isinstance(body.get('ros__parameters'), dict)
               } if isinstance(doc, dict) else {}
    last = {key: str(key).rstrip('/').rsplit('/', 1)[-1] for key in entries}
    wild = [key for key in entries if last[key] in ('*', '**')]
    named = [key for key in entries if last[key] == NODE_NAME]
    keys = wild + named
    if not keys and len(entries) == 1:
        keys = list(entries)
    if not keys:
        found = ', '.join(map(str, entries)) or 'none'
        raise ValueError(f'{path}: no parameters for {NODE_NAME} (expected "/**:" or '
                         f'"{NODE_NAME}:" with "ros__parameters:" inside; entries: {found})')
    values = {}
    for key in keys:
        values.update(_flatten(entries[key]))
    values = {n: v for n, v in values.items()
              if n not in RCLPY_PARAMS and not n.startswith('qos_overrides.')}
    check_names(values, f'{path}: ')
    try:
        return {n: coerce(n, v) for n, v in values.items()}
    except ValueError as err:
        raise ValueError(f'{path}: {err}') from None
