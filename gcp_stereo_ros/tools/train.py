"""
Train the Siamese GCP CNN (`gcp_stereo_ros.stereo.cnn.GcpNet`) with the paper's hinge loss.

For every left pixel (x, y) with known, non-occluded disparity d (rounded to an integer),
one positive right patch at x - d + o_pos, o_pos uniform in {-1, 0, 1}, and one negative at
x - d + o_neg, |o_neg| uniform in {4, ..., 8} with a random sign; loss
max(0, 0.2 + s_neg - s_pos), averaged. Pixels whose positive or negative falls outside the
right image are skipped. Where the right-view ground truth exists, pixels failing a
left-right GT check (|gt_right(x - d) - d| > 1) count as occluded, and the mirrored pair
(right and left images flipped horizontally and swapped, GT = flipped gt_right) is added
as one more training view.

Dense training: a step draws `--batch-size` random crops (32x256 left pixels; each from a
view chosen uniformly). The branch runs fully convolutionally over the left crop and over
the right-image columns its positives and negatives can reach (both taken from the
replicate-padded standardized image, exactly as `cnn.confidence` sees it), and the scores
of every GT pixel in the crop are gathered from the two descriptor maps: the same examples
as per-patch training at a small fraction of the cost. SGD with momentum, cosine learning
rate decay over all steps, fixed seed (numpy generator for crops and offsets, torch for the
initial weights).

The data split of the shipped weights (`gcp_stereo_ros/weights/gcp_cnn.pt`) is
config/cnn_split.yaml (`--split`): 33 KITTI 2015 road frames and 14 Middlebury scenes to
train, 10 other KITTI 2015 frames and 4 Middlebury scenes of other families to validate.
The README and the weights' meta hold the command that made them.

Validation (each epoch, frames `--val-frames`): hinge loss over all valid pixels with
offsets drawn from a fixed generator (seed 0, independent of `--seed`), and the GCP
density/accuracy (`gcp.gcp_quality`) of the raw cosine at `--val-thetas`, plus the
accuracy of plain winner-takes-all (WTA) on all valid pixels.

Calibration (after the last epoch, on the validation frames): an isotonic fit of the
probability that the CNN disparity is within 1 px of the truth given the raw cosine,
each frame weighted equally, stored in the weights file; `cnn.confidence` returns that
probability, which is what theta thresholds.
"""
import argparse
from dataclasses import dataclass
from pathlib import Path
import shlex
import sys
import time

import numpy as np
import torch
from tqdm import tqdm
import yaml

from .cli import console_main
from ..evaluation.datasets import load_frames
from ..stereo.cnn import confidence, GcpNet, network_input, PAD
from ..stereo.gcp import gcp_quality, right_view_agrees
from ..stereo.images import gray_pair

MARGIN = 0.2
CROP = (32, 256)  # left pixels per crop (rows, columns)
NEG_OFFSETS = (4, 8)
LR_CHECK_PX = 1.0
CALIBRATION_PX = 1.0  # the calibrated confidence is P(|CNN disparity - truth| <= 1 px)
CALIBRATION_BINS = 400


@dataclass
class View:
    """One training pair: padded standardized images (1, 1, H+8, W+8), integer GT (-1 = none)."""

    name: str
    left: torch.Tensor
    right: torch.Tensor
    disp: np.ndarray


def _padded(gray):
    return network_input(gray).contiguous(memory_format=torch.channels_last)


def _view(name, left, right, gt, valid, gt_right):
    lg, rg = gray_pair(left, right)
    valid = valid & np.isfinite(gt)
    d = np.where(valid, np.rint(np.nan_to_num(gt)), -1).astype(np.int64)
    if gt_right is not None:  # occluded pixels fail the left-right GT check
        valid &= right_view_agrees(np.where(valid, gt, 0), gt_right, LR_CHECK_PX)
        d[~valid] = -1
    return View(name, _padded(lg), _padded(rg), d)


def views(frame):
    """Training views of a frame: itself, plus its mirror when the right GT is known."""
    if frame.gt is None:
        raise ValueError(f'{frame.name}: no ground truth, cannot train on it')
    out = [_view(frame.name, frame.left, frame.right, frame.gt, frame.valid, frame.gt_right)]
    if frame.gt_right is not None:
        flip = np.fliplr
        out.append(_view(frame.name + ' (mirrored)', flip(frame.right), flip(frame.left),
                         flip(frame.gt_right), np.isfinite(frame.gt_right), flip(frame.gt)))
    return out


def pair_scores(net, view, rng, y0=0, x0=0, h=None, w=None):
    """(s_pos, s_neg) of every GT pixel in the left window [y0, y0+h) x [x0, x0+w)."""
    height, width = view.disp.shape
    h, w = h or height, w or width
    d = view.disp[y0:y0 + h, x0:x0 + w]
    ii, jj = np.nonzero(d >= 0)
    xr = x0 + jj - d[ii, jj]
    n = len(ii)
    pos = xr + rng.integers(-1, 2, n)
    neg = xr + rng.integers(NEG_OFFSETS[0], NEG_OFFSETS[1] + 1, n) * rng.choice((-1, 1), n)
    keep = (np.minimum(pos, neg) >= 0) & (np.maximum(pos, neg) < width)
    ii, jj, pos, neg = ii[keep], jj[keep], pos[keep], neg[keep]
    if len(ii) == 0:
        return None
    lo, hi = int(min(pos.min(), neg.min())), int(max(pos.max(), neg.max())) + 1
    fl = net.features(view.left[:, :, y0:y0 + h + 2 * PAD, x0:x0 + w + 2 * PAD])[0]
    fr = net.features(view.right[:, :, y0:y0 + h + 2 * PAD, lo:hi + 2 * PAD])[0]
    ii, jj, pos, neg = (torch.from_numpy(a) for a in (ii, jj, pos - lo, neg - lo))
    a = fl[:, ii, jj]
    return (a * fr[:, ii, pos]).sum(0), (a * fr[:, ii, neg]).sum(0)


def hinge(s_pos, s_neg):
    return torch.relu(MARGIN + s_neg - s_pos).mean()


def train_step(net, optimizer, train_views, rng, batch_size, bf16=False):
    """One SGD step on `batch_size` random crops; returns the loss (float)."""
    scores = []
    with torch.autocast('cpu', torch.bfloat16, enabled=bf16):
        while len(scores) < batch_size:
            view = train_views[rng.integers(len(train_views))]
            height, width = view.disp.shape
            h, w = min(CROP[0], height), min(CROP[1], width)
            s = pair_scores(net, view, rng, int(rng.integers(height - h + 1)),
                            int(rng.integers(width - w + 1)), h, w)
            if s is not None:
                scores.append(s)
    loss = hinge(torch.cat([s[0] for s in scores]), torch.cat([s[1] for s in scores]))
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    return loss.item()


def validate(net, frames, thetas):
    """{frame name: {'loss', 'wta_accuracy', 'gcp': {theta: (density %, accuracy %)}}}."""
    out = {}
    net.eval()
    with torch.no_grad():
        for f in frames:
            rng = np.random.default_rng(0)
            loss = float(hinge(*pair_scores(net, views(f)[0], rng)))
            cof_c, cof_d, _ = confidence(net, f.left, f.right, f.max_disp)
            stats = {f'{t:g}': gcp_quality(cof_c > t, cof_d, f.gt, f.valid) for t in thetas}
            out[f.name] = {'loss': loss,
                           'wta_accuracy': gcp_quality(cof_c >= 0, cof_d, f.gt, f.valid)[1],
                           'gcp': stats}
    net.train()
    return out


def fit_calibration(cosine, correct, weight, bins=CALIBRATION_BINS):
    """
    Fit P(correct | cosine) as a non-decreasing step function (isotonic regression).

    The samples are sorted by cosine and grouped into `bins` groups of equal count; pooling
    adjacent violators then makes the weighted fraction correct non-decreasing. Returns the
    knots (cosine, probability): the weighted mean cosine and fraction correct of each
    pooled group, cosines strictly increasing (what `cnn.calibrated` interpolates).
    """
    order = np.argsort(cosine, kind='stable')
    starts = np.unique(np.linspace(0, len(order), bins, endpoint=False).astype(np.int64))
    w = weight[order]
    groups = [np.add.reduceat(a, starts) for a in (w * correct[order], w, w * cosine[order])]
    pooled = []  # [weighted correct, weight, weighted cosine] per block
    for block in zip(*groups):
        pooled.append(list(block))
        while len(pooled) > 1 and pooled[-2][0] * pooled[-1][1] > pooled[-1][0] * pooled[-2][1]:
            last = pooled.pop()
            pooled[-1] = [a + b for a, b in zip(pooled[-1], last)]
    x = np.array([c / w for _, w, c in pooled])
    y = np.array([k / w for k, w, _ in pooled])
    keep = np.append(np.diff(x) > 0, True)  # equal cosines: the later (higher) probability
    return x[keep], y[keep]


def calibration_samples(net, frames):
    """
    Return (cosine, correct, weight) over the evaluated pixels of `frames`.

    cosine: the raw CNN confidence; correct: the CNN disparity within 1 px of the truth;
    weight: 1 / (the frame's evaluated pixels), so that every frame counts the same.
    """
    net.calibration = None
    out = []
    for f in frames:
        cof_c, cof_d, _ = confidence(net, f.left, f.right, f.max_disp)
        sel = f.valid & np.isfinite(f.gt)
        correct = np.abs(cof_d[sel] - f.gt[sel]) <= CALIBRATION_PX
        out.append((cof_c[sel], correct.astype(np.float64), np.full(sel.sum(), 1.0 / sel.sum())))
    return tuple(np.concatenate(a) for a in zip(*out))


def _select(sources, names, what):
    """Frames `names` (default: every frame with GT) found in the `sources`."""
    found = {}
    for source in sources:
        for f in load_frames(source):
            if f.gt is not None and (names is None or f.name in names):
                found.setdefault(f.name, f)
    missing = [n for n in names or () if n not in found]
    if missing:
        raise ValueError(f'{what} frames not found in {sources}: {missing}')
    if not found:
        raise ValueError(f'no {what} frames with ground truth in {sources}')
    return [found[n] for n in names] if names else list(found.values())


def _report(epoch, train_loss, val):
    parts = [f'epoch {epoch}: train loss {train_loss:.4f}']
    for name, v in val.items():
        gcps = ', '.join(f'theta {t}: {d:.1f}%/{a:.1f}%' for t, (d, a) in v['gcp'].items())
        parts.append(f'  {name}: val loss {v["loss"]:.4f}, WTA acc {v["wta_accuracy"]:.1f}%, '
                     f'GCP density/accuracy {gcps}')
    tqdm.write('\n'.join(parts))


def parse_args(argv):
    p = argparse.ArgumentParser(prog='gcp-stereo-train', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--dataset', action='append', required=True,
                   help='data folder (any supported layout, searched recursively) or '
                        '"motorcycle"; repeatable')
    p.add_argument('--frames', nargs='+',
                   help='training frame names (default: every frame with GT)')
    p.add_argument('--val-dataset', action='append',
                   help='validation sources (default: the --dataset ones)')
    p.add_argument('--val-frames', nargs='+',
                   help='validation frame names (default: no validation)')
    p.add_argument('--split', type=Path,
                   help="YAML file with the frame names under 'train:' and 'validation:' "
                        '(instead of --frames and --val-frames; e.g. config/cnn_split.yaml)')
    p.add_argument('--val-thetas', nargs='+', type=float, default=[0.5, 0.7, 0.8, 0.9])
    p.add_argument('--epochs', type=int, default=10)
    p.add_argument('--samples-per-epoch', type=int, default=2048, help='random crops per epoch')
    p.add_argument('--batch-size', type=int, default=4, help='crops per SGD step')
    p.add_argument('--lr', type=float, default=0.01)
    p.add_argument('--momentum', type=float, default=0.9)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--bf16', action='store_true',
                   help='bfloat16 autocast for the convolutions (about 2x faster on CPUs with '
                        'AVX512-BF16); weights, loss and validation stay float32')
    p.add_argument('--threads', type=int,
                   help="torch CPU threads (default: torch's choice); 1 is much faster than 2 "
                        'when other processes keep a core busy')
    p.add_argument('--checkpoint-dir', type=Path, help='save a checkpoint after every epoch here')
    p.add_argument('--resume', type=Path, help='continue from this checkpoint')
    p.add_argument('--out', type=Path, default=Path('gcp_cnn.pt'), help='final weights file')
    args = p.parse_args(argv)
    for k in ('epochs', 'samples_per_epoch', 'batch_size', 'threads'):
        if getattr(args, k) is not None and getattr(args, k) < 1:
            p.error(f'--{k.replace("_", "-")} must be at least 1')
    if args.lr <= 0 or not 0 <= args.momentum < 1:
        p.error('--lr must be positive and --momentum in [0, 1)')
    if args.split:
        if args.frames or args.val_frames:
            p.error('--split replaces --frames and --val-frames')
        try:
            split = yaml.safe_load(args.split.read_text())
            args.frames, args.val_frames = split['train'], split['validation']
        except (OSError, yaml.YAMLError, KeyError, TypeError) as err:
            p.error(f"--split {args.split}: expected YAML with 'train:' and 'validation:' "
                    f'lists of frame names ({err})')
    return args


@console_main('gcp-stereo-train')
def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    train_frames = _select(args.dataset, args.frames, 'training')
    val_frames = (_select(args.val_dataset or args.dataset, args.val_frames, 'validation')
                  if args.val_frames else [])
    train_views = [v for f in train_frames for v in views(f)]
    net = GcpNet().to(memory_format=torch.channels_last)
    optimizer = torch.optim.SGD(net.parameters(), lr=args.lr, momentum=args.momentum)
    steps = -(-args.samples_per_epoch // args.batch_size)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=args.epochs * steps)
    start, history, seconds = 0, [], 0.0
    if args.resume:
        ckpt = torch.load(args.resume, map_location='cpu', weights_only=True)
        net.load_state_dict(ckpt['net'])
        optimizer.load_state_dict(ckpt['optimizer'])
        scheduler.load_state_dict(ckpt['scheduler'])
        rng.bit_generator.state = ckpt['rng']
        torch.set_rng_state(ckpt['torch_rng'])
        start, history, seconds = ckpt['epoch'], ckpt['history'], ckpt['seconds']
    tqdm.write(f'training on {len(train_views)} views: {", ".join(v.name for v in train_views)}; '
               f'{steps} steps of {args.batch_size} crops per epoch')
    for epoch in range(start + 1, args.epochs + 1):
        t = time.perf_counter()
        net.train()
        bar = tqdm(range(steps), desc=f'epoch {epoch}/{args.epochs}', mininterval=2.0)
        losses = []
        for _ in bar:
            losses.append(train_step(net, optimizer, train_views, rng, args.batch_size, args.bf16))
            scheduler.step()
            bar.set_postfix(loss=f'{np.mean(losses[-50:]):.4f}')
        val = validate(net, val_frames, args.val_thetas)
        seconds += time.perf_counter() - t
        history.append({'epoch': epoch, 'train_loss': float(np.mean(losses)), 'seconds': seconds,
                        'val': val})
        _report(epoch, history[-1]['train_loss'], val)
        if args.checkpoint_dir:
            args.checkpoint_dir.mkdir(parents=True, exist_ok=True)
            torch.save({'net': net.state_dict(), 'optimizer': optimizer.state_dict(),
                        'scheduler': scheduler.state_dict(), 'epoch': epoch,
                        'rng': rng.bit_generator.state, 'torch_rng': torch.get_rng_state(),
                        'history': history, 'seconds': seconds},
                       args.checkpoint_dir / f'epoch_{epoch:03d}.pt')
    blob = {'state_dict': {k: v.contiguous() for k, v in net.state_dict().items()}}
    if val_frames:
        net.eval()
        with torch.no_grad():
            cosine, probability = fit_calibration(*calibration_samples(net, val_frames))
        blob['calibration'] = {'cosine': torch.from_numpy(cosine),
                               'probability': torch.from_numpy(probability)}
        tqdm.write('calibration (raw cosine -> P(CNN disparity within 1 px)): ' + ', '.join(
            f'{c:.3f} -> {p:.2f}' for c, p in zip(cosine[::len(cosine) // 12 or 1],
                                                  probability[::len(cosine) // 12 or 1])))
    command, rest = [], list(argv)  # resuming continues bit-identically: drop --resume
    while rest:
        arg = rest.pop(0)
        if arg == '--resume':
            rest.pop(0)
        elif not arg.startswith('--resume='):
            command.append(arg)
    meta = {'command': shlex.join(['gcp-stereo-train', *command]),
            'train_frames': [f.name for f in train_frames],
            'val_frames': [f.name for f in val_frames], 'seed': args.seed, 'epochs': args.epochs,
            'bf16': args.bf16, 'seconds': seconds, 'torch': str(torch.__version__),
            'history': history}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save({**blob, 'meta': meta}, args.out)
    tqdm.write(f'wrote {args.out} after {seconds:.0f} s of training')


if __name__ == '__main__':
    sys.exit(main())
