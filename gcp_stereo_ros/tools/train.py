"""
Train the Siamese GCP CNN (`gcp_stereo_ros.stereo.cnn.network.GcpNet`) with the paper's hinge loss.

The examples (`train_crops`): every GT pixel of random crops (32x256 left pixels; each from
a view chosen uniformly) against a positive and a negative right patch, max(0, 0.2 + s_neg -
s_pos) averaged; occluded pixels (failing a left-right GT check where the right GT exists)
left out, and the mirrored pair (right and left images flipped horizontally and swapped, GT
= flipped gt_right) added as one more view. With `--augment` every crop is resampled (scale,
shear, vertical jitter, contrast and brightness per view); `--hard-negatives F` scores a
fraction F of the pixels on their hardest negative. SGD with momentum, cosine learning rate
decay over all steps, fixed seed (numpy generator for crops and offsets, torch for the
initial weights); `--bf16` runs the convolutions in bfloat16. `--init` starts from trained
weights with a schedule of its own (fine-tuning; the new weights' meta keeps their command and
training time under 'init').

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
doc/evaluation.md ("The shipped CNN weights") and the weights' meta hold the command that
made them.

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
import os
from pathlib import Path
import shlex
import sys
import time

import numpy as np
import torch
from torch import distributed as dist
from torch.nn.parallel import DistributedDataParallel
from tqdm import tqdm
import yaml

from .cli import console_main
from .train_crops import Augment, crop_scores, CropLoss, draw_crop, hinge, views
from ..evaluation.datasets import load_frames
from ..stereo.backend import cnn_confidence
from ..stereo.cnn.network import GcpNet, load_net
from ..stereo.gcp import gcp_quality

CROP = (32, 256)  # left pixels per crop (rows, columns)
CALIBRATION_PX = 1.0  # the calibrated confidence is P(|CNN disparity - truth| <= 1 px)
CALIBRATION_BINS = 400


def train_step(model, optimizer, train_views, rng, batch_size, bf16=False, rank=0, world=1,
               aug=None, hard=0.0):
    """
    Take one SGD step on `batch_size` random crops; return (mean loss, pixels scored).

    `model`: a CropLoss, in DistributedDataParallel when `world` processes train. Each of
    them draws every crop from its `rng` (the same stream in all; `aug` and `hard` as
    `train_crops.draw_crop` takes them) and scores crops rank, rank + world, ... (as
    DistributedSampler deals out a batch); its summed loss is scaled so that DDP's average
    of the gradients is the gradient of the mean loss over the pixels of all the crops: the
    step one process takes.
    """
    crops = []
    while len(crops) < batch_size:
        crop = draw_crop(train_views[rng.integers(len(train_views))], rng, *CROP, aug, hard)
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
    return total.item() / pixels, pixels


def validate(net, frames, thetas):
    """{frame name: {'loss', 'wta_accuracy', 'gcp': {theta: (density %, accuracy %)}}}."""
    out = {}
    device = next(net.parameters()).device
    net.eval()
    with torch.no_grad():
        for f in frames:
            rng = np.random.default_rng(0)
            loss = float(hinge(*crop_scores(net, draw_crop(views(f, device)[0], rng))).mean())
            cof_c, cof_d, _ = cnn_confidence(net, f.left, f.right, f.max_disp, str(device))
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


def calibration_samples(net, frames, radius=0):
    """
    Return (cosine, correct, weight) over the evaluated pixels of `frames`.

    cosine: the raw CNN confidence (guided-filtered with `radius` > 0); correct: the CNN
    disparity within 1 px of the truth; weight: 1 / (the frame's evaluated pixels), so that
    every frame counts the same.
    """
    net.calibrations = {radius: None}
    device = next(net.parameters()).device
    out = []
    for f in frames:
        cof_c, cof_d, _ = cnn_confidence(net, f.left, f.right, f.max_disp, str(device),
                                         radius=radius)
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


def _report(epoch, record, val):
    parts = [f'epoch {epoch}: train loss {record["train_loss"]:.4f}, '
             f'{record["examples_per_second"]:.0f} examples/s']
    if val:
        parts[0] += (f'; mean val loss {np.mean([v["loss"] for v in val.values()]):.4f}, '
                     f'WTA acc {np.mean([v["wta_accuracy"] for v in val.values()]):.1f}%')
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
    p.add_argument('--augment', action='store_true',
                   help='resample every crop: scale, shear, vertical jitter, contrast and '
                        'brightness per view (train_crops.Augment)')
    p.add_argument('--hard-negatives', type=float, default=0.0, metavar='F',
                   help='fraction of the pixels scored on their hardest negative (0 to 1)')
    p.add_argument('--threads', type=int,
                   help="torch CPU threads (default: torch's choice); 1 is much faster than 2 "
                        'when other processes keep a core busy')
    p.add_argument('--device', default='cpu',
                   help="'cpu' or 'cuda' (under torchrun each process takes GPU LOCAL_RANK)")
    p.add_argument('--checkpoint-dir', type=Path, help='save a checkpoint after every epoch here')
    p.add_argument('--resume', type=Path, help='continue from this checkpoint')
    p.add_argument('--init', type=Path,
                   help='start from these weights (a gcp-stereo-train output) instead of random '
                        'ones, with a schedule of its own; the meta records them')
    p.add_argument('--out', type=Path, default=Path('gcp_cnn.pt'), help='final weights file')
    args = p.parse_args(argv)
    for k in ('epochs', 'samples_per_epoch', 'batch_size', 'threads'):
        if getattr(args, k) is not None and getattr(args, k) < 1:
            p.error(f'--{k.replace("_", "-")} must be at least 1')
    if args.lr <= 0 or not 0 <= args.momentum < 1:
        p.error('--lr must be positive and --momentum in [0, 1)')
    if not 0 <= args.hard_negatives <= 1:
        p.error(f'--hard-negatives must be in [0, 1], got {args.hard_negatives}')
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
def main(argv: list[str] | None = None) -> None:
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
    net = GcpNet()
    init = None
    if args.init:
        start_net = load_net(args.init)
        net.load_state_dict(start_net.state_dict())
        init = {'weights': str(args.init),
                **{k: start_net.meta.get(k) for k in ('command', 'seconds', 'init')}}
    net = net.to(device, memory_format=torch.channels_last)
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
    aug = Augment() if args.augment else None
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
        losses, pixels = [], 0
        for _ in bar:
            loss, n = train_step(model, optimizer, train_views, rng, args.batch_size, args.bf16,
                                 rank, world, aug, args.hard_negatives)
            losses.append(loss)
            pixels += n
            scheduler.step()
            bar.set_postfix(loss=f'{np.mean(losses[-50:]):.4f}')
        rate = pixels / (time.perf_counter() - t)
        val = validate(net, val_frames, args.val_thetas)
        seconds += time.perf_counter() - t
        history.append({'epoch': epoch, 'train_loss': float(np.mean(losses)), 'seconds': seconds,
                        'examples_per_second': rate, 'val': val})
        if rank > 0:
            continue
        _report(epoch, history[-1], val)
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
            'bf16': args.bf16, 'augment': args.augment,
            'hard_negatives': args.hard_negatives, 'processes': world, 'seconds': seconds,
            'torch': str(torch.__version__), 'init': init, 'history': history}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save({**blob, 'meta': meta}, args.out)
    tqdm.write(f'wrote {args.out} after {seconds:.0f} s of training')


if __name__ == '__main__':
    sys.exit(main())
