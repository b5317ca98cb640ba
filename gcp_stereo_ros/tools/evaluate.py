"""
gcp-stereo-eval: error rates of the stereo methods on datasets with ground truth.

Prints a table like the paper's Table 1 (% of ground-truth pixels with error > 3 px, per
frame and mean; unpublished pixels filled by the KITTI devkit's background interpolation,
as a KITTI submission is scored), then as KITTI reports them the density (% of ground-truth
pixels published), bad3_published (% of published pixels off by more than 3 px) and
near3_published (% of published pixels more than 3 px too near); the JSON rows also hold
bad1/2/5 of both kinds and mae. With ``align`` (the default) each frame's estimate
of the right view's misalignment is printed as it is made, and whether it was corrected
(the rows: misalignment, px, and aligned). Optionally writes colour-mapped disparity PNGs,
each with a colour bar of its scale in px (far to near).
"""
import argparse
import fnmatch
import json
from pathlib import Path
import sys
import time

import cv2
import numpy as np
from tqdm import tqdm
import yaml

from .cli import console_main, positive_int
from ..evaluation.datasets import list_frames, load_frame
from ..evaluation.metrics import error_rates
from ..evaluation.viz import disparity_picture, save_png
from ..stereo.backend import cnn_confidence
from ..stereo.cnn.weights import int8_entry
from ..stereo.config import PRESETS, StereoConfig
from ..stereo.costs import COSTS
from ..stereo.images import bin_area, gray_pair, upsample
from ..stereo.pipeline import StereoPipeline

# The peer, OpenCV StereoSGBM, as methods: its mode and the factor it matches at (2: both
# images area-binned as `downsample: 2` bins them, D / 2, the disparity x 2 at full size).
OPENCV_MODES: dict[str, tuple[int, int]] = {
    'opencv-sgbm-hh': (cv2.STEREO_SGBM_MODE_HH, 1),
    'opencv-sgbm': (cv2.STEREO_SGBM_MODE_SGBM, 1),
    'opencv-sgbm-3way': (cv2.STEREO_SGBM_MODE_SGBM_3WAY, 1),
    'opencv-sgbm-hh-half': (cv2.STEREO_SGBM_MODE_HH, 2),
    'opencv-sgbm-half': (cv2.STEREO_SGBM_MODE_SGBM, 2),
    'opencv-sgbm-3way-half': (cv2.STEREO_SGBM_MODE_SGBM_3WAY, 2),
}
# Fields that options set: --set (and gcp-stereo-plot's --grid) may not.
OPTION_FIELDS = {'cost': '--methods', 'use_gcp': '--methods', 'max_disp': '--max-disp',
                 'paths': '--paths'}
FIELDS = sorted(set(StereoConfig.__dataclass_fields__) - set(OPTION_FIELDS))  # --set's keys


def pipeline_methods() -> tuple[str, ...]:
    """Return the pipeline's methods: each registered cost alone and with GCPs ('sad+gcp')."""
    return (*COSTS, *(f'{cost}+gcp' for cost in COSTS))


def methods() -> tuple[str, ...]:
    """Return every method: the pipeline's, the CNN alone ('cnn'), OpenCV's."""
    return (*pipeline_methods(), 'cnn', *OPENCV_MODES)


def opencv_sgbm(left: np.ndarray, right: np.ndarray, max_disp: int,
                method: str = 'opencv-sgbm-hh', block: int = 5) -> np.ndarray:
    """
    Return the peer's disparity: OpenCV StereoSGBM in the mode of `method` (OPENCV_MODES).

    MODE_HH is full 8-path SGM on one core, MODE_SGBM 5 paths, MODE_SGBM_3WAY 4 paths on
    every core OpenCV uses; P1 = 8 block**2, P2 = 32 block**2. The disparity is float32 at
    the input's size, NaN where invalid. Its own invalidating filters (uniqueness,
    left-right, speckle) are off; it still leaves no estimate where x < max_disp can not be
    searched (filled by background interpolation for bad1..bad5).
    """
    mode, factor = OPENCV_MODES[method]
    lg, rg = gray_pair(left, right)
    lo, hi = min(lg.min(), rg.min()), max(lg.max(), rg.max())
    if lo < 0 or hi > 255 or hi <= 1:  # uint16 or float input: one joint scale to 0..255
        lg, rg = ((g - lo) * (255.0 / max(hi - lo, 1e-6)) for g in (lg, rg))
    shape = lg.shape
    if factor > 1:
        lg, rg = (bin_area(np.asarray(g, np.float32), factor) for g in (lg, rg))
    lg, rg = lg.astype(np.uint8), rg.astype(np.uint8)
    ndisp = -(-int(max_disp) // (16 * factor)) * 16
    sgbm = cv2.StereoSGBM.create(minDisparity=0, numDisparities=ndisp, blockSize=block,
                                 P1=8 * block * block, P2=32 * block * block, disp12MaxDiff=-1,
                                 uniquenessRatio=0, speckleWindowSize=0, mode=mode)
    disp = sgbm.compute(lg, rg).astype(np.float32) * (factor / 16.0)
    disp[disp < 0] = np.nan
    return upsample(disp, factor, shape) if factor > 1 else disp


def cnn_method(method):
    """Return the pipeline method whose config runs `method`'s CNN; None if it runs none."""
    if method == 'cnn':  # the CNN alone, with Census+GCP's CNN settings
        return 'census+gcp'
    return method if method.endswith('+gcp') else None


class Runner:
    """Runs any method of `methods()` on frames, sharing one loaded CNN."""

    def __init__(self, paths=None, overrides=None, preset='default'):
        self.paths = paths
        self.overrides = dict(overrides or {})
        self.preset = preset
        self._pipeline = None  # made by the first method run, then shared (its CNN too)

    def config(self, method, max_disp, point=None):
        """
        Return the StereoConfig of a pipeline method ('sad', 'census+gcp', ...).

        The preset's values for the cost ('default', 'paper' or 'realtime'), then the paths
        if given (None: the preset's), the overrides (a dict of StereoConfig fields), then
        those of a sweep's grid `point`.
        """
        cost, _, gcp = method.partition('+')
        paths = {} if self.paths is None else {'paths': self.paths}
        return StereoConfig.for_cost(cost, self.preset, use_gcp=bool(gcp), max_disp=max_disp,
                                     **paths, **{**self.overrides, **(point or {})})

    def pipeline(self, method, max_disp):
        config = self.config(method, max_disp)
        self._pipeline = (StereoPipeline(config) if self._pipeline is None
                          else self._pipeline.with_config(config))
        return self._pipeline

    def run(self, method, left, right, max_disp):
        """(disparity, StereoResult or None, seconds) of `method` on one pair."""
        if method not in methods():
            raise ValueError(f'unknown method {method!r}; choose from {methods()}')
        t = time.perf_counter()
        if method in OPENCV_MODES:
            return opencv_sgbm(left, right, max_disp, method), None, time.perf_counter() - t
        if method == 'cnn':  # winner-takes-all of the CNN confidence volume alone
            pipe = self.pipeline(cnn_method(method), max_disp)
            cfg = pipe.config
            cof_d = cnn_confidence(pipe.net, left, right, max_disp, cfg.device, cfg.precision,
                                   cfg.cnn_filter_radius).cof_d
            return cof_d.astype(np.float32), None, time.perf_counter() - t
        result = self.pipeline(method, max_disp)(left, right)
        return result.disparity, result, time.perf_counter() - t


def select_frames(sources, patterns):
    """(source, name) pairs of every frame in `sources` whose name matches a pattern."""
    chosen = []
    for source in sources:
        names = list_frames(source)
        picked = [n for n in names if not patterns or any(fnmatch.fnmatch(n, p) for p in patterns)]
        chosen += [(source, n) for n in picked]
    if not chosen:
        raise ValueError(f'no frame in {sources} matches {patterns}')
    return chosen


def table(rows, methods, key='bad3'):
    """Return the paper's Table 1 layout: one line per method, mean then per-frame values."""
    frames = list(dict.fromkeys(r['frame'] for r in rows))
    width = max(len(m) for m in methods) + 2
    lines = [f'{"method":<{width}}{"mean":>8}  ' + '  '.join(frames),
             f'{"":<{width}}{"(% of pixels with error > 3 px)" if key == "bad3" else key}']
    for m in methods:
        vals = {r['frame']: r[key] for r in rows if r['method'] == m}
        mean = float(np.mean(list(vals.values())))
        lines.append(f'{m:<{width}}{mean:8.2f}  '
                     + '  '.join(f'{vals[f]:>{len(f)}.2f}' for f in frames))
    return '\n'.join(lines)


def parse_overrides(items):
    """
    `KEY=VALUE` strings into a dict of StereoConfig fields.

    VALUE is parsed as YAML, but for a text field (cost, weights, device, precision), which
    takes it as written: `weights=off` is the file 'off', not YAML's false.
    """
    out = {}
    for item in items or []:
        key, sep, value = item.partition('=')
        if sep and key in OPTION_FIELDS:
            raise ValueError(f'--set {item!r}: {key} is set by {OPTION_FIELDS[key]}')
        if not sep or key not in FIELDS:
            raise ValueError(f'--set expects KEY=VALUE with KEY among {FIELDS}, '
                             f'got {item!r}')
        try:
            out[key] = (value if isinstance(getattr(StereoConfig, key, None), str)
                        else yaml.safe_load(value))
        except yaml.YAMLError:
            raise ValueError(f'--set {item!r}: VALUE is not a YAML scalar') from None
    return out


def add_options(ap, dataset_required=True):
    """Add the options that choose frames, methods and settings (all but --out) to `ap`."""
    ap.add_argument('--dataset', action='append', required=dataset_required,
                    help='dataset folder in any supported layout (searched recursively; for KITTI '
                         "the folder holding training/), or 'motorcycle'; repeatable")
    ap.add_argument('--frames', nargs='+', help='frame names or shell patterns (default: all)')
    ap.add_argument('--methods', nargs='+', default=['sad', 'census', 'opencv-sgbm-hh'],
                    choices=methods())
    ap.add_argument('--max-disp', type=positive_int,
                    help="disparities searched (default: each frame's own)")
    ap.add_argument('--paths', type=int, choices=(4, 8, 16),
                    help="SGM paths (default: the preset's, 16 but for realtime's 4)")
    ap.add_argument('--preset', default='default', choices=tuple(PRESETS),
                    help='parameter values before --set: the cross-validated defaults, '
                         "the paper's (Table 1's paper rows) or the real-time preset "
                         '(Census only; doc/speed.md)')
    ap.add_argument('--set', action='append', metavar='KEY=VALUE',
                    help='override a pipeline parameter (e.g. theta=0.7, precision=fp32); '
                    'repeatable')
    ap.add_argument('--json', type=Path, help='write one row per (method, frame) to this file')


def make_runner(args):
    """
    Return the Runner of the options of `add_options`.

    Raises ValueError, before any frame runs, if --preset and --set give a method of
    args.methods an invalid config, naming the method and the value.
    """
    runner = Runner(args.paths, parse_overrides(args.set), args.preset)
    for method in args.methods:
        run_by = cnn_method(method) or (None if method in OPENCV_MODES else method)
        if run_by is not None:
            try:
                runner.config(run_by, args.max_disp or 128)
            except ValueError as err:
                given = ''.join(f' --set {item}' for item in args.set or ())
                raise ValueError(f'{method} with --preset {args.preset}{given}: {err}') from None
    return runner


def evaluate_frame(runner, args, source, name):
    """
    Return (rows, note) of frame `name` of `source`: one row per method of args.methods.

    The note (or '') says how the frame's scoring departs from its benchmark's. Writes the
    colour-mapped disparity PNGs into args.out if set. Raises ValueError if the frame has
    no ground truth.
    """
    frame = load_frame(source, name)
    if frame.gt is None:
        raise ValueError(f'frame {name} has no ground truth to evaluate against')
    max_disp = args.max_disp or frame.max_disp
    rows, said = [], set()
    for method in args.methods:
        disp, result, seconds = runner.run(method, frame.left, frame.right, max_disp)
        rows.append({'method': method, 'frame': name, **error_rates(disp, frame.gt, frame.valid),
                     'seconds': seconds})
        if result is not None and (m := result.misalignment) is not None:
            rows[-1].update(misalignment=m.largest if m.known else None, aligned=m.verdict())
            if (line := f'{m.summary()}: {m.verdict()}') not in said:  # once per frame
                said.add(line)
                tqdm.write(f'{name}: {line}')
        if (cnn := cnn_method(method)) is not None:  # what precision 'auto' gave, per row
            from ..stereo.cnn.network import resolve_precision
            cfg = runner.config(cnn, max_disp)
            rows[-1]['precision'] = resolve_precision(cfg.precision, cfg.device,
                                                      int8_entry(cfg.weights) is not None)
        if args.out:
            save_png(args.out / f'{name.replace("/", "_")}_{method}.png',
                     disparity_picture(disp, max_disp))
    return rows, frame.note or ''


def print_results(rows, methods, notes):
    """Print the table of `rows` and the frames' notes ({frame name: note})."""
    print(table(rows, methods))
    for key in ('density', 'bad3_published', 'near3_published'):
        print(table(rows, methods, key))
    precisions = sorted({r['precision'] for r in rows if 'precision' in r})
    if precisions:
        print('CNN precision:', ' and '.join(precisions))
    for name, note in notes.items():
        if note:
            print(f'note: {name}: {note}')


def write_rows(path, rows):
    """Write `rows` as JSON to `path`, replacing it only once the file is complete."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f'.{path.name}.partial')
    partial.write_text(json.dumps(rows, indent=1))
    partial.replace(path)


@console_main('gcp-stereo-eval')
def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog='gcp-stereo-eval', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap)
    ap.add_argument('--out', type=Path, help='write colour-mapped disparity PNGs here, each '
                    'with a colour bar of its scale in px')
    args = ap.parse_args(argv)

    runner = make_runner(args)
    rows, notes = [], {}
    for source, name in tqdm(select_frames(args.dataset, args.frames), unit='frame', leave=False):
        frame_rows, notes[name] = evaluate_frame(runner, args, source, name)
        rows += frame_rows
    print_results(rows, args.methods, notes)
    if args.json:
        write_rows(args.json, rows)


if __name__ == '__main__':
    sys.exit(main())
