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

Several processes or machines: start it with torchrun (e.g. `torchrun --standalone
--nproc-per-node 2 -m gcp_stereo_ros.tools.train ...`). The processes form a
DistributedDataParallel group (gloo on the CPU, nccl with `--device cuda`, one GPU per
process); each draws the same crops and scores its share of them (crops rank, rank + N, ...),
and the averaged gradients make every step the step one process takes with the same
`--batch-size` (the global batch), so the losses and weights follow the one-process run.
Rank 0 alone validates, reports, writes checkpoints and the weights; checkpoints resume in
any number of processes.

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
import atexit
from dataclasses import dataclass
import os
from pathlib import Path
import shlex
import sys
import time

import numpy as np
import torch
from torch import distributed as dist, nn
from torch.nn.parallel import DistributedDataParallel
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


@dataclass
class Crop:
    """The GT pixels of a left window of a view, with their positive and negative columns."""

    view: View
    y0: int
    x0: int
    h: int
    w: int
    ii: np.ndarray  # rows and columns of the pixels in the window
    jj: np.ndarray
    pos: np.ndarray  # right-image columns
    neg: np.ndarray


def _padded(gray, device):
    return network_input(gray).to(device).contiguous(memory_format=torch.channels_last)


def _view(name, left, right, gt, valid, gt_right, device):
    lg, rg = gray_pair(left, right)
    valid = valid & np.isfinite(gt)
    d = np.where(valid, np.rint(np.nan_to_num(gt)), -1).astype(np.int64)
    if gt_right is not None:  # occluded pixels fail the left-right GT check
        valid &= right_view_agrees(np.where(valid, gt, 0), gt_right, LR_CHECK_PX)
        d[~valid] = -1
    return View(name, _padded(lg, device), _padded(rg, device), d)


def views(frame, device='cpu'):
    """Training views of a frame: itself, plus its mirror when the right GT is known."""
    if frame.gt is None:
        raise ValueError(f'{frame.name}: no ground truth, cannot train on it')
    out = [_view(frame.name, frame.left, frame.right, frame.gt, frame.valid, frame.gt_right,
                 device)]
    if frame.gt_right is not None:
        flip = np.fliplr
        out.append(_view(frame.name + ' (mirrored)', flip(frame.right), flip(frame.left),
                         flip(frame.gt_right), np.isfinite(frame.gt_right), flip(frame.gt),
                         device))
    return out


def draw_crop(view, rng, y0=0, x0=0, h=None, w=None):
    """
    Return the Crop of the left window [y0, y0+h) x [x0, x0+w), its offsets drawn from `rng`.

    None if no GT pixel of the window has its positive and negative inside the right image.
    """
    height, width = view.disp.shape
    h, w = h or height, w or width
    d = view.disp[y0:y0 + h, x0:x0 + w]
    ii, jj = np.nonzero(d >= 0)
    xr = x0 + jj - d[ii, jj]
    n = len(ii)
    pos = xr + rng.integers(-1, 2, n)
    neg = xr + rng.integers(NEG_OFFSETS[0], NEG_OFFSETS[1] + 1, n) * rng.choice((-1, 1), n)
    keep = (np.minimum(pos, neg) >= 0) & (np.maximum(pos, neg) < width)
    if not keep.any():
        return None
    return Crop(view, y0, x0, h, w, ii[keep], jj[keep], pos[keep], neg[keep])


def crop_scores(net, crop):
    """(s_pos, s_neg) of every pixel of `crop`."""
    c = crop
    lo, hi = int(min(c.pos.min(), c.neg.min())), int(max(c.pos.max(), c.neg.max())) + 1
    fl = net.features(c.view.left[:, :, c.y0:c.y0 + c.h + 2 * PAD, c.x0:c.x0 + c.w + 2 * PAD])[0]
    fr = net.features(c.view.right[:, :, c.y0:c.y0 + c.h + 2 * PAD, lo:hi + 2 * PAD])[0]
    ii, jj, pos, neg = (torch.from_numpy(a).to(fl.device)
                        for a in (c.ii, c.jj, c.pos - lo, c.neg - lo))
    a = fl[:, ii, jj]
    return (a * fr[:, ii, pos]).sum(0), (a * fr[:, ii, neg]).sum(0)


def hinge(s_pos, s_neg):
    """Return the hinge loss of every pixel."""
    return torch.relu(MARGIN + s_neg - s_pos)


class CropLoss(nn.Module):
    """The summed hinge loss of the pixels of some crops under `net` (what DDP wraps)."""

    def __init__(self, net):
        super().__init__()
        self.net = net

    def forward(self, crops):
        s_pos, s_neg = (torch.cat(s) for s in zip(*(crop_scores(self.net, c) for c in crops)))
        return hinge(s_pos, s_neg).sum()


def train_step(model, optimizer, train_views, rng, batch_size, bf16=False, rank=0, world=1):
    """
    Take one SGD step on `batch_size` random crops; return the loss (float).

    `model`: a CropLoss, in DistributedDataParallel when `world` processes train. Each of
    them draws every crop from its `rng` (the same stream in all) and scores crops rank,
    rank + world, ... (as DistributedSampler deals out a batch); its summed loss is scaled
    so that DDP's average of the gradients is the gradient of the mean loss over the pixels
    of all the crops: the step one process takes.
    """
    crops = []
    while len(crops) < batch_size:
        view = train_views[rng.integers(len(train_views))]
        height, width = view.disp.shape
        h, w = min(CROP[0], height), min(CROP[1], width)
        crop = draw_crop(view, rng, int(rng.integers(height - h + 1)),
                         int(rng.integers(width - w + 1)), h, w)
        if crop is not None:
            crops.append(crop)
    pixels = sum(len(c.ii) for c in crops)
    device = next(model.parameters()).device
    with torch.autocast(device.type, torch.bfloat16, enabled=bf16):
        total = model(crops[rank::world])
    optimizer.zero_grad()
    (total * (world / pixels)).backward()
    optimizer.step()
    total = total.detach()
    if world > 1:
        dist.all_reduce(total)
    return total.item() / pixels


def validate(net, frames, thetas):
    """{frame name: {'loss', 'wta_accuracy', 'gcp': {theta: (density %, accuracy %)}}}."""
    out = {}
    device = next(net.parameters()).device
    net.eval()
    with torch.no_grad():
        for f in frames:
            rng = np.random.default_rng(0)
            loss = float(hinge(*crop_scores(net, draw_crop(views(f, device)[0], rng))).mean())
            cof_c, cof_d, _ = confidence(net, f.left, f.right, f.max_disp, device)
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
    device = next(net.parameters()).device
    out = []
    for f in frames:
        cof_c, cof_d, _ = confidence(net, f.left, f.right, f.max_disp, device)
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
    p.add_argument('--device', default='cpu',
                   help="'cpu' or 'cuda' (under torchrun each process takes GPU LOCAL_RANK)")
    p.add_argument('--checkpoint-dir', type=Path, help='save a checkpoint after every epoch here')
    p.add_argument('--resume', type=Path, help='continue from this checkpoint')
    p.add_argument('--out', type=Path, default=Path('gcp_cnn.pt'), help='final weights file')
    args = p.parse_args(argv)
    for k in ('epochs', 'samples_per_epoch', 'batch_size', 'threads'):
        if getattr(args, k) is not None and getattr(args, k) < 1:
            p.error(f'--{k.replace("_", "-")} must be at least 1')
    if args.lr <= 0 or not 0 <= args.momentum < 1:
        p.error('--lr must be positive and --momentum in [0, 1)')
    if not (args.device == 'cpu' or args.device.startswith('cuda')):
        p.error(f"--device must be 'cpu' or 'cuda[:N]', got {args.device!r}")
    world = int(os.environ.get('WORLD_SIZE', '1'))
    if args.batch_size < world:
        p.error(f'--batch-size {args.batch_size} is less than the {world} processes: '
                'each needs a crop per step')
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


def distributed(device):
    """
    Return (rank, processes, device) of this process; under torchrun, join its process group.

    torchrun sets WORLD_SIZE, RANK and LOCAL_RANK. The group talks gloo on the CPU and nccl
    on CUDA, where each process takes GPU LOCAL_RANK.
    """
    world = int(os.environ.get('WORLD_SIZE', '1'))
    if world == 1:
        return 0, 1, torch.device(device)
    if device.startswith('cuda'):
        device = f'cuda:{os.environ["LOCAL_RANK"]}'
        torch.cuda.set_device(device)
    dist.init_process_group('nccl' if device.startswith('cuda') else 'gloo')
    atexit.register(dist.destroy_process_group)
    return dist.get_rank(), world, torch.device(device)


@console_main('gcp-stereo-train')
def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    rank, world, device = distributed(args.device)  # rank 0 validates, reports and saves
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    train_frames = _select(args.dataset, args.frames, 'training')
    val_frames = (_select(args.val_dataset or args.dataset, args.val_frames, 'validation')
                  if args.val_frames and rank == 0 else [])
    train_views = [v for f in train_frames for v in views(f, device)]
    net = GcpNet().to(device, memory_format=torch.channels_last)
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
    model = CropLoss(net) if world == 1 else DistributedDataParallel(CropLoss(net))
    if rank == 0:
        tqdm.write(f'training on {len(train_views)} views: '
                   f'{", ".join(v.name for v in train_views)}; {steps} steps of '
                   f'{args.batch_size} crops per epoch, in {world} process(es)')
    for epoch in range(start + 1, args.epochs + 1):
        t = time.perf_counter()
        net.train()
        bar = tqdm(range(steps), desc=f'epoch {epoch}/{args.epochs}', mininterval=2.0,
                   disable=rank > 0)
        losses = []
        for _ in bar:
            losses.append(train_step(model, optimizer, train_views, rng, args.batch_size,
                                     args.bf16, rank, world))
            scheduler.step()
            bar.set_postfix(loss=f'{np.mean(losses[-50:]):.4f}')
        val = validate(net, val_frames, args.val_thetas)
        seconds += time.perf_counter() - t
        history.append({'epoch': epoch, 'train_loss': float(np.mean(losses)), 'seconds': seconds,
                        'val': val})
        if rank > 0:
            continue
        _report(epoch, history[-1]['train_loss'], val)
        if args.checkpoint_dir:
            args.checkpoint_dir.mkdir(parents=True, exist_ok=True)
            torch.save({'net': net.state_dict(), 'optimizer': optimizer.state_dict(),
                        'scheduler': scheduler.state_dict(), 'epoch': epoch,
                        'rng': rng.bit_generator.state, 'torch_rng': torch.get_rng_state(),
                        'history': history, 'seconds': seconds},
                       args.checkpoint_dir / f'epoch_{epoch:03d}.pt')
    if rank > 0:
        return
    blob = {'state_dict': {k: v.contiguous().cpu() for k, v in net.state_dict().items()}}
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
            'bf16': args.bf16, 'processes': world, 'seconds': seconds,
            'torch': str(torch.__version__), 'history': history}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save({**blob, 'meta': meta}, args.out)
    tqdm.write(f'wrote {args.out} after {seconds:.0f} s of training')


if __name__ == '__main__':
    sys.exit(main())
