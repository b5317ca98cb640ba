"""
gcp-stereo-plot: the paper's experiment figures as matplotlib PNGs.

  sweep  error (> 3 px), GCP density and GCP accuracy of a method over a parameter grid, per frame
         (Figure 4: `--grid theta=0:1:0.05`); the best grid point is printed, which is how
         theta, c_hi, c_low, P1 and P2 are chosen by cross-validation.
  bars   per-frame improvement of +GCP over its baseline from a `gcp-stereo-eval --json`
         file (Figures 5 and 6).
  sparsification
         error (> 3 px) among the x % most confident published pixels against x, for the
         disparity_confidence, the CNN confidence and the oracle (the error itself), mean
         over the frames, and each curve's area: how confidence measures are compared.
  rate   rate against error: mean dense error (> 3 px, unpublished pixels interpolated) on the
         frames given against the time of a `gcp-stereo-bench --json` run, of our modes and
         OpenCV StereoSGBM's that the bench timed (its `modes`), as a table and a plot; time as
         a ratio to OpenCV MODE_SGBM_3WAY at full size, measured in the same bench.
  training
         the curves of a `gcp-stereo-train` run from its weights or a checkpoint: training
         and validation hinge loss, WTA accuracy and GCP density/accuracy per epoch (means
         over the validation frames), against hours of training.
"""
import argparse
import itertools
import json
from pathlib import Path
import sys

import matplotlib
import numpy as np

from .cli import console_main, positive_int
from .evaluate import (FIELDS, OPENCV_MODES, opencv_sgbm, parse_overrides, pipeline_methods,
                       Runner, select_frames)
from ..evaluation.datasets import load_frame
from ..evaluation.metrics import error_rates, sparsification, sparsification_area
from ..stereo.config import CNN_FIELDS, StereoConfig
from ..stereo.costs import COSTS
from ..stereo.gcp import gcp_quality
from ..stereo.pipeline import StereoPipeline

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402, I100  (after choosing the headless backend)


def parse_grid(items):
    """
    `name=lo:hi:step` or `name=v1,v2,...` -> {name: [values]} (StereoConfig field names).

    A list takes numbers and true/false (gcp_lr_check=true,false).
    """
    grid = {}
    for item in items:
        name, _, spec = item.partition('=')
        try:
            if ':' in spec:
                lo, hi, step = (float(v) for v in spec.split(':'))
                values = [round(v, 6) for v in np.arange(lo, hi + step / 2, step)]
            else:
                values = [_grid_value(v) for v in spec.split(',')]
        except (ValueError, ZeroDivisionError):
            values = []
        if name not in FIELDS or not values:
            raise ValueError(f'--grid expects NAME=LO:HI:STEP or NAME=V1,V2,... with NAME among '
                             f'{FIELDS}, got {item!r}')
        grid[name] = values
    return grid


def _grid_value(text):
    """Return the int, float or bool (true, false) that `text` spells; ValueError if none."""
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    if text.lower() not in ('true', 'false'):
        raise ValueError(text)
    return text.lower() == 'true'


def sweep(args):
    grid = parse_grid(args.grid)
    runner = Runner(args.paths, parse_overrides(args.set))
    rows = []
    for source, name in select_frames(args.dataset, args.frames):
        frame = load_frame(source, name)
        max_disp = args.max_disp or frame.max_disp
        base = runner.pipeline(args.method, max_disp)
        outputs = {}  # the CNN's outputs of this frame per CNN_FIELDS, run once each
        for values in itertools.product(*grid.values()):
            point = dict(zip(grid, values))
            try:
                config = runner.config(args.method, max_disp, point)
            except ValueError as err:  # e.g. P2 < P1: not a valid set-up, so not a candidate
                invalid = err
                continue
            pipe = base.with_config(config)
            key = tuple(getattr(config, f) for f in CNN_FIELDS)
            result = pipe(frame.left, frame.right, cnn=outputs.get(key))
            row = {'frame': name, **point,
                   'bad3': error_rates(result.disparity, frame.gt, frame.valid)['bad3']}
            if result.gcp is not None:
                outputs[key] = result.cnn
                row['gcp_density'], row['gcp_accuracy'] = gcp_quality(
                    result.gcp, result.cof_d, frame.gt, frame.valid)
            rows.append(row)
        if not rows:
            raise ValueError(f'no point of the grid is a valid set-up: {invalid}')
        print(f'{name}: best ' + _best(rows, name, grid))
    frames = list(dict.fromkeys(r['frame'] for r in rows))
    means = {}
    for r in rows:
        means.setdefault(tuple(r[k] for k in grid), []).append(r['bad3'])
    best = min(means, key=lambda k: np.mean(means[k]))
    print(f'mean over {len(frames)} frame(s): best '
          + ', '.join(f'{k}={v}' for k, v in zip(grid, best))
          + f' -> {np.mean(means[best]):.2f} % bad3')
    args.out.mkdir(parents=True, exist_ok=True)
    stem = 'sweep_' + args.method.replace('+', '_')
    (args.out / f'{stem}.json').write_text(json.dumps(rows, indent=1))
    _plot_sweep(rows, grid, dict(zip(grid, best)), args.method, args.out / f'{stem}.png')


def _best(rows, frame, grid):
    r = min((r for r in rows if r['frame'] == frame), key=lambda r: r['bad3'])
    return ', '.join(f'{k}={r[k]}' for k in grid) + f' -> {r["bad3"]:.2f} % bad3'


def _plot_sweep(rows, grid, best, method, path):
    """
    Plot error (and GCP density and accuracy) against the first grid parameter.

    The other grid parameters are fixed at their best mean values.
    """
    x_name = next(iter(grid))
    fixed = {k: v for k, v in best.items() if k != x_name}
    keys = ('bad3', 'gcp_density', 'gcp_accuracy') if 'gcp_density' in rows[0] else ('bad3',)
    fig, axes = plt.subplots(1, len(keys), figsize=(5 * len(keys), 4), squeeze=False)
    axes = axes[0]
    for frame in dict.fromkeys(r['frame'] for r in rows):
        sel = [r for r in rows if r['frame'] == frame and all(r[k] == v for k, v in fixed.items())
               # no GCP at all (theta 1): every pixel C_hi, 100 % error
               and r.get('gcp_density', 1) > 0]
        xs = [r[x_name] for r in sel]
        for ax, key in zip(axes, keys):
            ax.plot(xs, [r[key] for r in sel], marker='.', label=frame)
    switch = all(isinstance(v, bool) for v in grid[x_name])
    for ax, title in zip(axes, ('error > 3 px (%)', 'GCP density (% of GT pixels)',
                                'GCP accuracy (%)')):
        if switch:
            ax.set_xticks([False, True], ['false', 'true'])
        ax.set_xlabel(x_name)
        ax.set_title(f'{method}: {title}')
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    if fixed:
        fig.suptitle(', '.join(f'{k}={v}' for k, v in fixed.items()), fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f'wrote {path}')


def sparsify(args):
    runner = Runner(args.paths, {**parse_overrides(args.set), 'min_confidence': 0.0})
    curves = {'disparity_confidence': [], 'CNN confidence': [], 'oracle': []}
    for source, name in select_frames(args.dataset, args.frames):
        frame = load_frame(source, name)
        _, result, _ = runner.run(args.method, frame.left, frame.right,
                                  args.max_disp or frame.max_disp)
        if result.disparity_confidence is None:
            raise ValueError(f'{args.method}: no confidence fit beside the weights '
                             '(python -m gcp_stereo_ros.tools.fit_confidence)')
        sel = np.isfinite(result.disparity) & np.isfinite(frame.gt)
        if frame.valid is not None:
            sel &= frame.valid
        err = np.abs(result.disparity[sel] - frame.gt[sel])
        scores = {'disparity_confidence': result.disparity_confidence[sel], 'oracle': -err}
        if result.cof_c is not None:
            scores['CNN confidence'] = result.cof_c[sel]
        for key, score in scores.items():
            fractions, rates = sparsification(err > 3, score)
            curves[key].append(rates)
    fig, ax = plt.subplots(figsize=(6, 4))
    for key, per_frame in curves.items():
        if per_frame:
            rates = np.mean(per_frame, axis=0)
            area = sparsification_area(fractions, rates)
            print(f'{key}: area {area:.3f}, error at 100 % {rates[-1]:.2f} %')
            ax.plot(100 * fractions, rates, marker='.', label=f'{key} (area {area:.2f})')
    ax.set_xlabel('most confident published pixels kept (%)')
    ax.set_ylabel('error > 3 px among them (%)')
    ax.set_title(f'{args.method}: sparsification, mean of {len(curves["oracle"])} frame(s)')
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / ('sparsification_' + args.method.replace('+', '_') + '.png')
    fig.savefig(path, dpi=110)
    print(f'wrote {path}')


def rate(args: argparse.Namespace) -> None:
    try:
        bench = json.loads(args.bench.read_text())
        modes = {k: bench['modes'][k] for k in args.modes or bench['modes']}
        seconds = {k: bench['stages'][k] for k in modes}
        peer = bench['stages']['opencv_sgbm_3way']
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f'{args.bench}: not a gcp-stereo-bench --json file that timed '
                         f'these modes ({e!r})') from None
    frames = [load_frame(*f) for f in select_frames(args.dataset, args.frames)]
    rows, pipe = [], None
    for name, mode in modes.items():
        for frame in frames:
            if mode['method'] in OPENCV_MODES:
                disp = opencv_sgbm(frame.left, frame.right, frame.max_disp, mode['method'])
            else:  # as the bench made it
                cost, _, gcp = mode['method'].partition('+')
                config = StereoConfig.for_cost(cost, mode['preset'], use_gcp=bool(gcp),
                                               max_disp=frame.max_disp, **mode['set'])
                pipe = StereoPipeline(config) if pipe is None else pipe.with_config(config)
                disp = pipe(frame.left, frame.right).disparity
            rows.append({'mode': name, 'frame': frame.name,
                         **error_rates(disp, frame.gt, frame.valid)})  # type: ignore[arg-type]
    table = [{'mode': name, 'seconds': seconds[name], 'x_3way': seconds[name] / peer,
              **{k: float(np.mean([r[k] for r in rows if r['mode'] == name]))
                 for k in ('bad3', 'density', 'bad3_published')}} for name in modes]
    load = ' -> '.join(f'{v:.2f}' for v in bench.get('load_average', ())) or 'unknown'
    where = f'{bench.get("device", "unknown CPU")}; load average {load}'
    print(f'{where}; errors: mean of {len(frames)} frame(s)')
    print(f'{"mode":<28}{"seconds":>8}{"x 3WAY":>8}{"pairs/s":>9}{"bad3 %":>8}'
          f'{"density %":>10}{"bad3 of published %":>21}')
    for t in table:
        print(f'{t["mode"]:<28}{t["seconds"]:8.3f}{t["x_3way"]:8.2f}{1 / t["seconds"]:9.2f}'
              f'{t["bad3"]:8.2f}{t["density"]:10.1f}{t["bad3_published"]:21.2f}')
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / 'rate.json').write_text(json.dumps({'table': table, 'rows': rows}, indent=1))
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for t in table:
        ours = not t['mode'].startswith('opencv_')
        ax.plot(t['x_3way'], t['bad3'], 'o' if ours else 's', color='C0' if ours else 'C1')
        ax.annotate(t['mode'], (t['x_3way'], t['bad3']), fontsize=7, xytext=(4, 3),
                    textcoords='offset points')
    ax.set_xscale('log')
    ax.set_xlabel('time of a KITTI pair (1242x375, D 128), x OpenCV MODE_SGBM_3WAY')
    ax.set_ylabel(f'dense error > 3 px (%), mean of {len(frames)} frame(s)')
    ax.set_title(f'ours (blue) and OpenCV (orange); {where}', fontsize=8)
    ax.grid(alpha=0.3, which='both')
    fig.tight_layout()
    fig.savefig(args.out / 'rate.png', dpi=110)
    print(f'wrote {args.out / "rate.png"}')


def bars(args):
    try:
        rows = json.loads(args.json.read_text())
        frames = list(dict.fromkeys(r['frame'] for r in rows))
        err = {(r['method'], r['frame']): r['bad3'] for r in rows}
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f'{args.json}: not a gcp-stereo-eval --json file ({e!r})') from None
    pairs = [(c, f'{c}+gcp') for c in COSTS
             if all((m, f) in err for m in (c, f'{c}+gcp') for f in frames)]
    if not pairs:
        raise ValueError(f'{args.json} needs both a cost and its +gcp method on every frame')
    fig, axes = plt.subplots(1, len(pairs), figsize=(max(6, 1.2 * len(frames)) * len(pairs), 4),
                             squeeze=False)
    for ax, (base, gcp) in zip(axes[0], pairs):
        x = np.arange(len(frames))
        ax.bar(x - 0.2, [err[base, f] for f in frames], 0.4, label=f'{base.upper()}+SGM')
        ax.bar(x + 0.2, [err[gcp, f] for f in frames], 0.4, label=f'{base.upper()}+GCP+SGM')
        for i, f in enumerate(frames):
            cut = 100 * (1 - err[gcp, f] / err[base, f]) if err[base, f] else 0.0
            ax.annotate(f'{-cut:+.0f}%', (i + 0.2, err[gcp, f]), ha='center', va='bottom',
                        fontsize=8)
        ax.set_xticks(x, ['/'.join(f.split('/')[-2:]) for f in frames], rotation=30, ha='right')
        ax.set_ylabel('error > 3 px (%)')
        ax.legend()
        ax.grid(axis='y', alpha=0.3)
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / 'gcp_improvement.png'
    fig.savefig(path, dpi=110)
    print(f'wrote {path}')


def training(args):
    import torch  # only this figure needs it
    try:
        blob = torch.load(args.weights, map_location='cpu', weights_only=True)
        history = blob['meta']['history'] if 'meta' in blob else blob['history']
        hours = np.array([h['seconds'] for h in history]) / 3600
        val = [h['val'] for h in history]
    except (OSError, RuntimeError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f'{args.weights}: not gcp-stereo-train weights or a checkpoint of it '
                         f'({e!r})') from None
    if not history or not val[0]:
        raise ValueError(f'{args.weights}: no validated epoch to draw')

    def mean(key, pick=lambda v: v):
        return [np.mean([pick(f[key]) for f in v.values()]) for v in val]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    axes[0].plot(hours, [h['train_loss'] for h in history], marker='.', label='training')
    axes[0].plot(hours, mean('loss'), marker='.', label='validation')
    axes[0].set_title('hinge loss')
    axes[1].plot(hours, mean('wta_accuracy'), marker='.')
    axes[1].set_title('CNN alone (WTA): accuracy within 3 px, mean (%)')
    for theta in val[0][next(iter(val[0]))]['gcp']:
        for i, (what, style) in enumerate((('density', '--'), ('accuracy', '-'))):
            axes[2].plot(hours, mean('gcp', lambda g, t=theta, i=i: g[t][i]), style,
                         marker='.', label=f'{what}, raw cosine > {theta}')
    axes[2].set_title('GCPs: density and accuracy, mean (%)')
    for ax in axes:
        ax.set_xlabel('hours of training')
        ax.grid(alpha=0.3)
    axes[0].legend()
    axes[2].legend(fontsize=7)
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / 'training.png'
    fig.savefig(path, dpi=110)
    print(f'{len(history)} epochs, {hours[-1]:.2f} h: final validation loss {mean("loss")[-1]:.4f}'
          f', WTA accuracy {mean("wta_accuracy")[-1]:.2f} %')
    print(f'wrote {path}')


@console_main('gcp-stereo-plot')
def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog='gcp-stereo-plot', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest='command', required=True)
    sp = sub.add_parser('sweep', help='error and GCP quality over a parameter grid')
    sp.add_argument('--dataset', action='append', required=True)
    sp.add_argument('--frames', nargs='+')
    sp.add_argument('--method', choices=pipeline_methods(),
                    default='census+gcp')
    sp.add_argument('--grid', action='append', required=True, metavar='NAME=LO:HI:STEP|V1,V2',
                    help='StereoConfig field and its values, e.g. theta=0:1:0.05 or p2=64,128; '
                         'repeatable')
    sp.add_argument('--set', action='append', metavar='KEY=VALUE', help='fixed parameter override')
    sp.add_argument('--max-disp', type=positive_int)
    sp.add_argument('--paths', type=int, default=16, choices=(4, 8, 16))
    sp.add_argument('--out', type=Path, default=Path('out/plots'))
    sp.set_defaults(run=sweep)
    bp = sub.add_parser('bars', help='per-frame improvement of +GCP over its baseline')
    bp.add_argument('--json', type=Path, required=True, help='a gcp-stereo-eval --json file')
    bp.add_argument('--out', type=Path, default=Path('out/plots'))
    bp.set_defaults(run=bars)
    zp = sub.add_parser('sparsification', help='error of the most confident x %% against x')
    zp.add_argument('--dataset', action='append', required=True)
    zp.add_argument('--frames', nargs='+')
    zp.add_argument('--method', choices=pipeline_methods(),
                    default='census+gcp')
    zp.add_argument('--set', action='append', metavar='KEY=VALUE', help='parameter override')
    zp.add_argument('--max-disp', type=positive_int)
    zp.add_argument('--paths', type=int, default=16, choices=(4, 8, 16))
    zp.add_argument('--out', type=Path, default=Path('out/plots'))
    zp.set_defaults(run=sparsify)
    rp = sub.add_parser('rate', help='error against time, ours and OpenCV, from a bench run')
    rp.add_argument('--bench', type=Path, required=True, help='a gcp-stereo-bench --json file')
    rp.add_argument('--dataset', action='append', required=True)
    rp.add_argument('--frames', nargs='+')
    rp.add_argument('--modes', nargs='+', help='modes of the bench to show (default: all its '
                    '`modes`), e.g. pipeline pipeline_downsample2 opencv_sgbm_3way')
    rp.add_argument('--out', type=Path, default=Path('out/plots'))
    rp.set_defaults(run=rate)
    tp = sub.add_parser('training', help='loss and validation curves of a training run')
    tp.add_argument('--weights', type=Path, required=True,
                    help='gcp-stereo-train weights or one of its checkpoints')
    tp.add_argument('--out', type=Path, default=Path('out/plots'))
    tp.set_defaults(run=training)
    args = ap.parse_args(argv)
    args.run(args)


if __name__ == '__main__':
    sys.exit(main())
