"""Siamese CNN matching confidence (Zhong, Su, Cao, Li: GCPs via CNN for stereo matching).

Each branch: 4 conv layers (3x3, 64 maps, ReLU after each, no pooling, no padding) map a
9x9 patch of per-image standardized gray intensity to a 64-d descriptor; both branches
share weights. The paper normalizes the inner product of the two descriptors to [0, 1];
we L2-normalize each descriptor (eps-safe, an all-zero descriptor stays zero). After the
final ReLU the descriptors are non-negative, so their inner product is a cosine already in
[0, 1]: that is the confidence.

Dense use (`confidence`): the branch runs fully convolutionally over each whole image
(replicate-padded by 4, so every pixel gets a descriptor), once per image. The confidence
volume Vol(x, y, d) = <f_L(x, y), f_R(x - d, y)> is then streamed by a numba kernel on the
CPU that keeps only cof_c = max_d Vol and cof_d = argmax_d Vol (first maximum on ties);
cells with x - d < 0 have Vol = 0.
"""
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from numba import njit, prange
from torch import nn

from .images import gray_pair, standardize

PATCH = 9
FEATURES = 64
PAD = PATCH // 2
EPS = 1e-8
DEFAULT_WEIGHTS = Path(__file__).parent / 'weights' / 'gcp_cnn.pt'


class GcpNet(nn.Module):
    """Shared branch of the Siamese net: 9x9 patch -> 64-d L2-normalized descriptor."""

    def __init__(self):
        super().__init__()
        layers = []
        for i in range(4):
            layers += [nn.Conv2d(1 if i == 0 else FEATURES, FEATURES, 3), nn.ReLU()]
        self.branch = nn.Sequential(*layers)

    def features(self, x):
        """Valid (unpadded) convolution of (N, 1, H, W) -> L2-normalized (N, 64, H-8, W-8)."""
        return F.normalize(self.branch(x).float(), dim=1, eps=EPS)

    def forward(self, left_patches, right_patches):
        """Confidences (N,) in [0, 1] of (N, 1, 9, 9) left/right patch pairs."""
        for name, p in (('left_patches', left_patches), ('right_patches', right_patches)):
            if p.ndim != 4 or tuple(p.shape[1:]) != (1, PATCH, PATCH):
                raise ValueError(f'{name} must have shape (N, 1, {PATCH}, {PATCH}), got {tuple(p.shape)}')
        return (self.features(left_patches) * self.features(right_patches)).sum(dim=1).flatten()

    def descriptors(self, gray):
        """Per-pixel descriptors of standardized gray image(s), replicate-padded by 4.

        (H, W) -> (64, H, W); (N, 1, H, W) -> (N, 64, H, W). Float32, L2-normalized.
        """
        single = gray.ndim == 2
        x = gray[None, None] if single else gray
        if x.ndim != 4 or x.shape[1] != 1:
            raise ValueError(f'expected an (H, W) or (N, 1, H, W) tensor, got {tuple(gray.shape)}')
        f = self.features(F.pad(x, (PAD,) * 4, mode='replicate'))
        return f[0] if single else f


def load_net(path=None, device='cpu'):
    """GcpNet in eval mode with the weights at `path` (default: the shipped weights).

    The file holds {'state_dict': ..., 'meta': {...}} (see `gcp_stereo_ros.train`).
    Raises FileNotFoundError if it does not exist, ValueError if it cannot be read as such.
    """
    path = Path(DEFAULT_WEIGHTS if path is None else path)
    if not path.is_file():
        raise FileNotFoundError(f'GCP CNN weights not found: {path}')
    try:
        blob = torch.load(path, map_location='cpu', weights_only=True)
        net = GcpNet()
        net.load_state_dict(blob['state_dict'])
    except Exception as e:  # any unreadable or mismatching file is reported the same way
        raise ValueError(f'GCP CNN weights file {path} is corrupt or not a GcpNet checkpoint: {e}') from e
    net.meta = blob.get('meta', {})
    return net.to(device).eval()


@njit(inline='always', fastmath=True)
def _dot(a, b):
    s = np.float32(0.0)
    for c in range(a.shape[0]):
        s += a[c] * b[c]
    return min(s, np.float32(1.0))  # a cosine; rounding may overshoot 1 by an ulp


@njit(parallel=True, cache=True, fastmath=True)
def _best_match(fl, fr, max_disp):
    """Streamed max / first argmax over d of <fl[y, x], fr[y, x - d]> (HWC float32 inputs)."""
    h, w, _ = fl.shape
    cof_c = np.zeros((h, w), np.float32)
    cof_d = np.zeros((h, w), np.int32)
    for y in prange(h):
        for x in range(w):
            best = np.float32(-1.0)
            arg = 0
            for d in range(min(max_disp, x + 1)):
                v = _dot(fl[y, x], fr[y, x - d])
                if v > best:
                    best = v
                    arg = d
            cof_c[y, x] = best
            cof_d[y, x] = arg
    return cof_c, cof_d


@njit(parallel=True, cache=True, fastmath=True)
def _volume(fl, fr, max_disp):
    """The full (H, W, D) confidence volume, same arithmetic as `_best_match`."""
    h, w, _ = fl.shape
    vol = np.zeros((h, w, max_disp), np.float32)
    for y in prange(h):
        for x in range(w):
            for d in range(min(max_disp, x + 1)):
                vol[y, x, d] = _dot(fl[y, x], fr[y, x - d])
    return vol


def image_descriptors(net, left, right, device='cpu', bf16=False):
    """Descriptors of a pair as two float32 (H, W, 64) C-contiguous numpy arrays.

    Each image is standardized on its own; both go through the net as one batch with the
    net in channels_last (1.6x faster convs on CPU than the default), under bf16 autocast if
    `bf16` (another ~2x on AVX512-BF16 CPUs; normalization stays float32).
    """
    lg, rg = gray_pair(left, right)
    x = torch.from_numpy(np.stack([standardize(lg), standardize(rg)])[:, None]).to(device)
    net.to(memory_format=torch.channels_last)  # in place; the 1-channel input alone cannot select it
    with torch.inference_mode(), torch.autocast(torch.device(device).type, torch.bfloat16, enabled=bf16):
        f = net.descriptors(x)  # channels_last, so the permute below is a free view
    f = f.permute(0, 2, 3, 1).cpu().contiguous().numpy()
    return f[0], f[1]


def best_match(left_desc, right_desc, max_disp):
    """(cof_c, cof_d) of two (H, W, C) float32 descriptor arrays (see `confidence`)."""
    fl = np.ascontiguousarray(left_desc, np.float32)
    fr = np.ascontiguousarray(right_desc, np.float32)
    if fl.ndim != 3 or fl.shape != fr.shape:
        raise ValueError(f'descriptors must be two (H, W, C) arrays of one shape, got {fl.shape} and {fr.shape}')
    _check_max_disp(max_disp, fl.shape[1])
    return _best_match(fl, fr, int(max_disp))


def _check_max_disp(max_disp, width):
    if not (isinstance(max_disp, (int, np.integer)) and 1 <= max_disp <= width):
        raise ValueError(f'max_disp must be an integer in [1, image width {width}], got {max_disp!r}')


def confidence(net, left, right, max_disp, device='cpu', bf16=False, volume=False):
    """CNN matching confidence of a rectified pair for disparities 0..max_disp-1.

    `left`/`right`: anything `images.gray_pair` accepts. The convolutions run with torch on
    `device` ('cpu' or 'cuda'; `bf16` turns on bfloat16 autocast, about 2x faster on CPUs
    with AVX512-BF16); the correlation always runs in a numba kernel on the CPU, streaming
    over d without materializing the volume.

    Returns (cof_c, cof_d): float32 (H, W) max_d Vol in [0, 1] and int32 (H, W) argmax_d Vol
    (first maximum on ties), where Vol(y, x, d) = 0 for x - d < 0. With `volume=True` also
    returns the float32 (H, W, max_disp) volume Vol (memory-hungry; for tests and plots).
    """
    lg, rg = gray_pair(left, right)
    _check_max_disp(max_disp, lg.shape[1])
    fl, fr = image_descriptors(net, lg, rg, device, bf16)
    cof_c, cof_d = best_match(fl, fr, max_disp)
    return (cof_c, cof_d, _volume(fl, fr, int(max_disp))) if volume else (cof_c, cof_d)
