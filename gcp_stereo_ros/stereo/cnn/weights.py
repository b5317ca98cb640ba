"""
The CNN weights and their side file: where they are and what they carry besides the net.

A weights file `<name>.pt` (written by `tools.train`) holds the net's state and the
calibration of its unfiltered confidence. Beside it, `<name>.confidence.json` (the side
file, written by `tools.fit_confidence`) holds, under `calibration_key(r)`, the calibration
of the confidence guided-filtered with radius r, under `method_key(cfg)`, the fit of the
disparity confidence of each method, and under INT8_KEY the int8 CNN's activation ranges
(`cnn.int8`). Every kind of entry is read here, and only here.
"""
import json
from pathlib import Path

import numpy as np

from ..config import StereoConfig
from ..disparity_confidence import CONFIDENCE_FEATURES, ConfidenceFit

DEFAULT_WEIGHTS = Path(__file__).parents[2] / 'weights' / 'gcp_cnn.pt'
CALIBRATION_KEY = 'cnn_filter_radius='  # + the radius: a calibration's key in the side file
INT8_KEY = 'int8'  # the int8 CNN's activation ranges and steps in the side file

Knots = tuple[np.ndarray, np.ndarray]


def weights_path(weights: str | Path | None) -> Path:
    """Return the path of `weights` ('' or None: the shipped weights)."""
    return Path(weights or DEFAULT_WEIGHTS)


def side_file(weights: str | Path | None) -> Path:
    """Return the side file beside `weights` ('' or None: the shipped weights)."""
    return weights_path(weights).with_suffix('.confidence.json')


def read_side_file(weights: str | Path | None) -> dict:
    """Return the side file's entries ({} without one); ValueError if it cannot be read."""
    path = side_file(weights)
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f'cannot read the confidence fits {path}: {err}') from None


def calibration_key(radius: int) -> str:
    """Return the side file's key of the calibration for `cnn_filter_radius` r > 0."""
    return f'{CALIBRATION_KEY}{radius}'


def parse_calibration(stored: dict | None, path: Path) -> Knots | None:
    """
    Return the (cosine, probability) knots of a stored calibration, or None for None.

    ValueError unless both are finite 1-D arrays of one length >= 2, the cosines strictly
    increasing and the probabilities non-decreasing in [0, 1].
    """
    if stored is None:
        return None
    try:
        x, y = (np.asarray(stored[k], np.float64) for k in ('cosine', 'probability'))
        ok = (x.ndim == y.ndim == 1 and len(x) == len(y) >= 2 and np.isfinite(x).all()
              and np.isfinite(y).all() and (np.diff(x) > 0).all() and (np.diff(y) >= 0).all()
              and y[0] >= 0 and y[-1] <= 1)
    except (KeyError, TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f'{path}: invalid CNN confidence calibration')
    return x, y


def cnn_calibrations(own: dict | None, weights: Path) -> dict[int, Knots | None]:
    """
    Return {radius: knots} of the CNN confidence: 0 from the weights' `own`, r > 0 beside.

    None knots (radius 0 of weights without a calibration) mean the raw cosine.
    """
    calibrations = {0: parse_calibration(own, weights)}
    for key, entry in read_side_file(weights).items():
        radius = key.removeprefix(CALIBRATION_KEY)
        if key.startswith(CALIBRATION_KEY) and radius.isdigit() and int(radius) > 0:
            calibrations[int(radius)] = parse_calibration(entry or {}, side_file(weights))
    return calibrations


def int8_entry(weights: str | Path | None) -> dict | None:
    """Return the int8 entry beside `weights` ({'ranges', 'clips', 'frames'}), None if none."""
    return read_side_file(weights).get(INT8_KEY)


def method_key(cfg: StereoConfig) -> str:
    """
    Return the side file's key of cfg's disparity-confidence fit.

    'census+gcp', 'sad', ...; with the CNN filter '+filter' and its radius; matched at
    1 / downsample, '@' and the factor: 'census+gcp+filter4@2'.
    """
    key = cfg.cost + ('+gcp' if cfg.use_gcp else '')
    key += f'+filter{cfg.cnn_filter_radius}' if cfg.use_gcp and cfg.cnn_filter_radius else ''
    return key + (f'@{cfg.downsample}' if cfg.downsample > 1 else '')


def confidence_fit(cfg: StereoConfig) -> ConfidenceFit | None:
    """Return the disparity-confidence fit of cfg's method and weights, None if none ships."""
    entry = read_side_file(cfg.weights).get(method_key(cfg))
    if entry is None:
        return None
    try:
        if entry['features'] != list(CONFIDENCE_FEATURES):
            raise ValueError(f'fitted on features {entry["features"]}, this version has '
                             f'{list(CONFIDENCE_FEATURES)}: fit it again '
                             '(tools/fit_confidence.py)')
        return ConfidenceFit(entry['coef'], entry['knots'])
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f'cannot read the confidence fit {side_file(cfg.weights)}: '
                         f'{err}') from None
