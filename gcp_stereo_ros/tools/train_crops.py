"""
The training examples of `gcp-stereo-train`: views, crops, augmentation and hard negatives.

For every left pixel (x, y) of a crop with known, non-occluded disparity d (rounded to an
integer), one positive right patch at x - d + o_pos, o_pos uniform in {-1, 0, 1}, and the
negatives at x - d + o, |o| in {4, ..., 8} (ten candidates); its loss is
max(0, 0.2 + s_neg - s_pos), where s_neg is one candidate drawn uniformly or, for a
`hard` fraction of the pixels, the candidate the net scores highest (a hard negative).
Pixels whose positive, or every negative, falls outside the right image are skipped.

The branch runs fully convolutionally over the left crop and over the right-image columns
its positives and negatives reach (both cut from, or sampled in, the replicate-padded
standardized image exactly as `cnn.confidence` sees it), and the scores of every GT pixel
are gathered from the two descriptor maps: the examples of per-patch training at a small
fraction of the cost.

Augmentation (`Augment`) resamples a crop of both views with one scale and horizontal shear
(the disparity scales with the image, the rows stay epipolar), shifts the right view by a
sub-pixel vertical offset (rectification error), and changes contrast and brightness of the
two standardized views by different amounts. Rotation is left out: rotating both views of a
dense crop moves a match off its row by d sin(angle), 1 px at d = 57 for 1 degree.
"""
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from ..stereo.cnn.network import network_input, PAD
from ..stereo.gcp import right_view_agrees
from ..stereo.images import gray_pair

MARGIN = 0.2
NEG_OFFSETS = np.array([o for a in range(4, 9) for o in (-a, a)])  # |o| in [4, 8]
LR_CHECK_PX = 1.0


@dataclass
class View:
    """One training pair: padded standardized images (1, 1, H+8, W+8), GT (NaN = none)."""

    name: str
    left: torch.Tensor
    right: torch.Tensor
    gt: np.ndarray


@dataclass
class Crop:
    """
    The GT pixels of a left window, with their positive and negative right columns.

    `left`: the padded window (1, 1, h+8, w+8); `right`: the padded right columns the
    pixels reach (1, 1, h+8, cols+8); `ii`, `jj`: the pixels' rows and columns in the
    window; `pos` (n,), `neg` (n, 10): their right columns in `right`; `neg_ok` (n, 10):
    which negatives lie in the right image; `hard` (n,): pixels scored on their hardest
    negative; `pick` (n,): the candidate of the others.
    """

    left: torch.Tensor
    right: torch.Tensor
    ii: np.ndarray
    jj: np.ndarray
    pos: np.ndarray
    neg: np.ndarray
    neg_ok: np.ndarray
    hard: np.ndarray
    pick: np.ndarray


@dataclass(frozen=True)
class Augment:
    """
    Ranges of the random changes of a crop (each drawn uniformly, scales in log).

    `scale`: of both views; `shear`: horizontal, columns per row, of both views;
    `vertical`: px, of the right view; `contrast`, `brightness`: of both standardized
    views, and `view_contrast`, `view_brightness`: the further change of each view.
    """

    scale: float = 1.25
    shear: float = 0.1
    vertical: float = 0.25
    contrast: float = 1.3
    brightness: float = 0.5
    view_contrast: float = 1.1
    view_brightness: float = 0.2


def _padded(gray, device):
    return network_input(gray).to(device).contiguous(memory_format=torch.channels_last)


def _view(name, left, right, gt, valid, gt_right, device):
    lg, rg = gray_pair(left, right)
    valid = valid & np.isfinite(gt)
    if gt_right is not None:  # occluded pixels fail the left-right GT check
        valid &= right_view_agrees(np.where(valid, gt, 0), gt_right, LR_CHECK_PX)
    return View(name, _padded(lg, device), _padded(rg, device),
                np.where(valid, gt, np.nan).astype(np.float32))


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


class _Warp:
    """
    Where a crop pixel lies in its view: x = x0 + u / s + k (v - h/2), y = y0 + v / s + dy.

    (u, v): column and row in the crop (u may lie left or right of it on the right view);
    the identity (s = 1, k = dy = 0) cuts the view's pixels as they are.
    """

    def __init__(self, x0, y0, h, s=1.0, k=0.0, dy=0.0):
        self.x0, self.y0, self.h, self.s, self.k, self.dy = x0, y0, h, s, k, dy

    def identity(self, right):
        """Tell whether the crop is the view's pixels as they are (cut, not resampled)."""
        return (self.s == 1.0 and self.k == 0.0 and not (right and self.dy)
                and float(self.x0).is_integer() and float(self.y0).is_integer())

    def x(self, u, v):
        return self.x0 + u / self.s + self.k * (v - self.h / 2)

    def y(self, v, right=False):
        return self.y0 + v / self.s + (self.dy if right else 0.0)

    def sample(self, image, u0, u1, right=False):
        """Return the padded crop (1, 1, h+8, u1-u0+8) of crop columns [u0, u1) of a view."""
        if self.identity(right):
            x0, y0 = int(self.x0) + u0, int(self.y0)
            return image[:, :, y0:y0 + self.h + 2 * PAD, x0:x0 + u1 - u0 + 2 * PAD]
        v = torch.arange(-PAD, self.h + PAD, dtype=torch.float64)[:, None]
        u = torch.arange(u0 - PAD, u1 + PAD, dtype=torch.float64)[None, :]
        x = self.x(u, v) + PAD  # in the padded image
        y = (self.y(v, right) + PAD).expand_as(x)
        size = image.shape[-2:]
        grid = torch.stack((2 * x / (size[1] - 1) - 1, 2 * y / (size[0] - 1) - 1), -1)
        return F.grid_sample(image, grid[None].to(image.device, torch.float32),
                             mode='bilinear', padding_mode='border', align_corners=True)


def _log_uniform(rng, factor):
    """Return a factor in [1 / factor, factor], uniform in log."""
    return np.exp(rng.uniform(-1, 1) * np.log(factor))


def _photometric(rng, aug):
    """(contrast, brightness) of the left and the right view."""
    c = _log_uniform(rng, aug.contrast)
    b = rng.uniform(-aug.brightness, aug.brightness)
    return [(c * _log_uniform(rng, aug.view_contrast),
             b + rng.uniform(-aug.view_brightness, aug.view_brightness)) for _ in range(2)]


def draw_crop(view, rng, h=None, w=None, aug=None, hard=0.0):
    """
    Return a random Crop of h x w left pixels of `view` (default: all of it), or None.

    Its place, offsets, hard pixels (a fraction `hard`) and, with `aug` (an Augment), its
    changes are drawn from `rng`. None if no GT pixel of it has a positive and a negative
    inside the right image.
    """
    height, width = view.gt.shape
    h, w = min(h or height, height), min(w or width, width)
    if aug is None:
        warp = _Warp(int(rng.integers(width - w + 1)), int(rng.integers(height - h + 1)), h)
    else:
        s = _log_uniform(rng, aug.scale)
        span = (min(w / s, width - 1), min(h / s, height - 1))
        warp = _Warp(rng.uniform(0, width - 1 - span[0]), rng.uniform(0, height - 1 - span[1]),
                     h, s, rng.uniform(-aug.shear, aug.shear),
                     rng.uniform(-aug.vertical, aug.vertical))
    vv, uu = np.mgrid[:h, :w]
    xs, ys = np.rint(warp.x(uu, vv)).astype(np.int64), np.rint(warp.y(vv)).astype(np.int64)
    inside = (xs >= 0) & (xs < width) & (ys >= 0) & (ys < height)
    gt = np.full((h, w), np.nan, np.float32)
    gt[inside] = view.gt[ys[inside], xs[inside]] * warp.s
    ii, jj = np.nonzero(np.isfinite(gt))
    xr = jj - np.rint(gt[ii, jj]).astype(np.int64)  # crop columns of the right view
    n = len(ii)
    pos = xr + rng.integers(-1, 2, n)
    neg = xr[:, None] + NEG_OFFSETS

    def in_right(u, v):
        x = warp.x(u, v)
        return (x >= 0) & (x <= width - 1)

    neg_ok = in_right(neg, ii[:, None])
    keep = in_right(pos, ii) & neg_ok.any(1)
    hard_px = rng.uniform(size=n) < hard
    pick = np.argmax(rng.uniform(size=neg.shape) * neg_ok, 1)  # a valid candidate, uniformly
    if not keep.any():
        return None
    ii, jj, pos, neg, neg_ok = ii[keep], jj[keep], pos[keep], neg[keep], neg_ok[keep]
    lo = int(min(pos.min(), neg[neg_ok].min()))
    hi = int(max(pos.max(), neg[neg_ok].max())) + 1
    left, right = warp.sample(view.left, 0, w), warp.sample(view.right, lo, hi, right=True)
    if aug is not None:
        (cl, bl), (cr, br) = _photometric(rng, aug)
        left, right = left * cl + bl, right * cr + br
    return Crop(left, right, ii, jj, pos - lo, np.clip(neg - lo, 0, hi - lo - 1), neg_ok,
                hard_px[keep], pick[keep])


def crop_scores(net, crop):
    """(s_pos, s_neg) of every pixel of `crop`."""
    c = crop
    fl, fr = net.features(c.left)[0], net.features(c.right)[0]
    dev = fl.device
    ii, jj, pos, neg = (torch.from_numpy(a).to(dev) for a in (c.ii, c.jj, c.pos, c.neg))
    a = fl[:, ii, jj]
    s_pos = (a * fr[:, ii, pos]).sum(0)
    s_all = (a[:, :, None] * fr[:, ii[:, None], neg]).sum(0)  # (n, 10)
    s_all = s_all.masked_fill(~torch.from_numpy(c.neg_ok).to(dev), -2.0)
    hardest = s_all.max(1).values
    drawn = s_all.gather(1, torch.from_numpy(c.pick).to(dev)[:, None])[:, 0]
    return s_pos, torch.where(torch.from_numpy(c.hard).to(dev), hardest, drawn)


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
