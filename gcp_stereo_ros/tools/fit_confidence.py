r"""
python -m gcp_stereo_ros.tools.fit_confidence: fit the confidences beside the CNN weights.

For each `--cnn-filter-radius` r > 0 first the calibration of the CNN confidence
guided-filtered with it (stereo.cnn_filter), as the training tool fits the unfiltered one:
P(CNN disparity within 1 px) of the filtered maximum (`train.fit_calibration`), written
under weights.calibration_key(r), which theta then reads; likewise for r / f, the radius the
filter runs with at each `--downsample` f (StereoConfig.matched_radius). Then the
confidence of the final disparity, for each method, downsample factor and radius.

The disparity confidence (stereo.disparity_confidence) is P(|d - truth| <= 3 px) of each pixel
that the search did not cut short. Fitted on the validation frames only (each frame weighted
equally): a logistic regression of CONFIDENCE_FEATURES, then an isotonic map of its score
(`train.fit_calibration`, as the CNN's confidence is calibrated). The pixels are those of
each method's default pipeline that `valid_window` keeps (the features are those of the
WTA disparity before any test), so the fit holds whatever other test is on. Writes one
entry per method, downsample factor and radius (weights.method_key) into the side file of
the weights (weights.side_file), keeping the other entries.

With `--int8` it fits only the activation ranges of the int8 CNN (stereo.cnn_int8) on the
split's training frames, and writes them under weights.INT8_KEY.

The shipped fits (the manual, doc/published.md):
    python -m gcp_stereo_ros.tools.fit_confidence --dataset ../shared/data \
        --split config/cnn_split.yaml --methods census+gcp --downsample 1 2 4 \
        --cnn-filter-radius 0 1 2 3 4 5 6 7 8
    python -m gcp_stereo_ros.tools.fit_confidence --dataset ../shared/data \
        --split config/cnn_split.yaml --int8
"""
import argparse
import json
import sys

import numpy as np
from tqdm import tqdm
import yaml

from .cli import console_main
from .evaluate import pipeline_methods, Runner, select_frames
from ..evaluation.datasets import load_frame
from ..stereo.cnn.weights import calibration_key, INT8_KEY, method_key, side_file
from ..stereo.config import DOWNSAMPLE, RANGES, StereoConfig, UNFILTERED
from ..stereo.disparity_confidence import (CONFIDENCE_FEATURES, CONFIDENCE_PX, ConfidenceFit,
                                           features)
from ..stereo.images import gray_pair, subsample, upsample
from ..stereo.postprocess import cut_short

RIDGE = 1e-6  # keeps the logistic fit defined when a feature is constant on the samples
ITERATIONS = 25


def logistic(x, y, w):
    """Return the weights (intercept first) of a weighted logistic regression (IRLS)."""
    x = np.column_stack([np.ones(len(x)), x]).astype(np.float64)
    coef = np.zeros(x.shape[1])
    for _ in range(ITERATIONS):
        p = 1.0 / (1.0 + np.exp(-np.clip(x @ coef, -30, 30)))
        s = w * p * (1 - p)
        step = np.linalg.solve((x * s[:, None]).T @ x + RIDGE * np.eye(len(coef)),
                               x.T @ (w * (y - p)) - RIDGE * coef)
        coef += step
        if np.abs(step).max() < 1e-8:
            break
    return coef


def fit(feats, correct, weight):
    """Return the ConfidenceFit of n samples: features (n features, n), correct, weight."""
    from .train import fit_calibration  # torch is loaded with it
    coef = logistic(feats.T, correct.astype(np.float64), weight)
    model = ConfidenceFit(coef, ([0.0, 1.0], [0.0, 1.0]))
    knots = fit_calibration(model.score(feats).astype(np.float64), correct, weight)
    return ConfidenceFit(coef, knots)


def samples(result, config, gt, valid):
    """
    Return (features, correct) of the n pixels with ground truth that `valid_window` keeps.

    features: (n features, n) float32, correct: (n,) bool.

    `result`: of `config` with every invalidation off. The features are computed on the
    matching grid (1 / downsample), as the pipeline computes them; each full-size pixel is a
    sample with its matching pixel's features.
    """
    f, shape = config.downsample, result.disparity.shape
    grid = (shape[0] // f, shape[1] // f)
    disp, consistent, m, cof_c, cof_d, gcp = (
        None if a is None else subsample(a, f, grid)
        for a in (result.disparity, result.consistent, result.margin, result.cof_c,
                  result.cof_d, result.gcp))
    disp = disp / np.float32(f)
    cof_d = None if cof_d is None else cof_d // f
    sel = ~upsample(cut_short(disp, config), f, shape) & np.isfinite(gt)
    if valid is not None:
        sel &= valid
    feats = np.stack([upsample(plane, f, shape)[sel]
                      for plane in features(disp, consistent, m, cof_c, cof_d, gcp)])
    return feats, np.abs(result.disparity[sel] - gt[sel]) <= CONFIDENCE_PX


def split_frames(path, part='validation'):
    """Return the frame names of `part` ('validation' or 'train') of a split file."""
    doc = yaml.safe_load(open(path))
    if not isinstance(doc, dict) or not doc.get(part):
        raise ValueError(f'{path}: no {part} frames')
    return list(doc[part])


def fit_int8(args, path, fits):
    """Fit the int8 CNN's activation ranges on the split's training frames into `fits`."""
    from ..stereo.cnn.network import load_net, network_input  # torch is loaded with them
    from ..stereo.cnn.int8 import fit as fit_ranges
    frames = [load_frame(source, name) for source, name in select_frames(
        args.dataset, split_frames(args.split, 'train'))]
    inputs = (network_input(*gray_pair(f.left, f.right)) for f in frames)
    fits[INT8_KEY] = fit_ranges(load_net(args.weights or None), inputs, [f.name for f in frames])
    path.write_text(json.dumps(fits, indent=1) + '\n')
    print(f'{INT8_KEY}: {len(frames)} training frames, clips {fits[INT8_KEY]["clips"]}; '
          f'wrote {path}')


@console_main('fit_confidence')
def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog='python -m gcp_stereo_ros.tools.fit_confidence',
                                 description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--dataset', action='append', required=True)
    which = ap.add_mutually_exclusive_group(required=True)
    which.add_argument('--frames', nargs='+', help='validation frame names or patterns')
    which.add_argument('--split', help="a split file: its 'validation' frames")
    ap.add_argument('--methods', nargs='+', default=['census+gcp'],
                    choices=pipeline_methods())
    ap.add_argument('--downsample', nargs='+', type=int, default=[1], choices=DOWNSAMPLE,
                    help='fit for each of these downsample factors (each has its own fit)')
    ap.add_argument('--weights', default='', help="CNN weights ('' = the shipped ones)")
    low, high = map(int, RANGES['cnn_filter_radius'])
    ap.add_argument('--cnn-filter-radius', type=int, nargs='+', default=[0], metavar='R',
                    choices=range(low, high + 1),
                    help=f'fit for each of these radii of the CNN filter ({low} to {high}; '
                    'each r > 0 also gets its CNN calibration, fitted first)')
    ap.add_argument('--int8', action='store_true',
                    help="fit only the int8 CNN's activation ranges, on the split's training "
                    'frames (needs --split)')
    args = ap.parse_args(argv)
    if args.int8 and not args.split:
        ap.error('--int8 fits on the training frames of a --split')

    path = side_file(args.weights)
    fits = json.loads(path.read_text()) if path.is_file() else {}
    if args.int8:
        fit_int8(args, path, fits)
        return
    frames = [load_frame(source, name) for source, name in select_frames(
        args.dataset, split_frames(args.split) if args.split else args.frames)]
    # the radii filtered with: each r, and r / f on the matching grid of each factor f
    matched = sorted({StereoConfig(cnn_filter_radius=radius, downsample=factor).matched_radius
                      for radius in args.cnn_filter_radius for factor in [1, *args.downsample]
                      if radius})
    if matched:
        from .train import calibration_samples, fit_calibration  # torch is loaded with them
        from ..stereo.cnn.network import load_net
        net = load_net(args.weights or None)
    for radius in matched:
        cosine, probability = fit_calibration(*calibration_samples(net, frames, radius))
        fits[calibration_key(radius)] = {'cosine': cosine.tolist(),
                                         'probability': probability.tolist(),
                                         'frames': [frame.name for frame in frames]}
        path.write_text(json.dumps(fits, indent=1) + '\n')  # the pipelines below read it
        print(f'{calibration_key(radius)}: {len(frames)} frames, {len(cosine)} knots, '
              f'P(within 1 px) from {probability[0]:.3f} to {probability[-1]:.3f}')
    for radius in args.cnn_filter_radius:
        for factor in args.downsample:
            runner = Runner(overrides={'weights': args.weights, 'downsample': factor,
                                       'cnn_filter_radius': radius, **UNFILTERED})
            for method in args.methods:
                if radius and not method.endswith('+gcp'):
                    continue  # the filter is of the GCPs' CNN volume
                parts = []
                for frame in tqdm(frames, desc=method, unit='frame', leave=False):
                    _, result, _ = runner.run(method, frame.left, frame.right, frame.max_disp)
                    config = runner.config(method, frame.max_disp)
                    feats, correct = samples(result, config, frame.gt, frame.valid)
                    parts.append((feats, correct, np.full(len(correct), 1.0 / len(correct))))
                feats, correct, weight = zip(*parts)
                model = fit(np.concatenate(feats, axis=1), np.concatenate(correct),
                            np.concatenate(weight))
                key = method_key(config)
                fits[key] = {'features': list(CONFIDENCE_FEATURES), 'coef': model.coef.tolist(),
                             'knots': [k.tolist() for k in model.knots],
                             'frames': [frame.name for frame in frames]}
                print(f'{key}: {len(frames)} frames, confidence from '
                      f'{model.knots[1][0]:.3f} to {model.knots[1][-1]:.3f}')
    path.write_text(json.dumps(fits, indent=1) + '\n')
    print(f'wrote {path}')


if __name__ == '__main__':
    sys.exit(main())
