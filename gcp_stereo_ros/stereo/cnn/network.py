"""
Siamese CNN matching confidence (Zhong, Su, Cao, Li: GCPs via CNN for stereo matching).

Each branch: 4 conv layers (3x3, 64 maps, ReLU after each, no pooling, no padding) map a
9x9 patch of per-image standardized gray intensity to a 64-d descriptor; both branches
share weights. The paper normalizes the inner product of the two descriptors to [0, 1];
we L2-normalize each descriptor (eps-safe, an all-zero descriptor stays zero). After the
final ReLU the descriptors are non-negative, so their inner product is a cosine already in
[0, 1]: that is the confidence.

Dense use (`confidence`): the branch runs fully convolutionally over each image
(replicate-padded by 4, so every pixel gets a descriptor), once per pixel. A numba kernel
on the CPU L2-normalizes the raw descriptors (float32, or bfloat16 widened exactly) and
streams the confidence volume Vol(y, x, d) = <f_L(y, x), f_R(y, x - d)>, keeping only
cof_c = max_d Vol and cof_d = argmax_d Vol (first maximum on ties; cells with x - d < 0
have Vol = 0), and the right view's CNN disparity cof_dr(y, xr) = argmax of Vol(y, xr + d, d)
over d < min(D, W - xr), for GCPs that both views agree on (`gcp.select`). Row y of Vol
needs only row y of both descriptor images, so both steps run on strips of STRIP_ROWS rows:
the activations of a strip stay in the CPU caches and the descriptors of the whole images
are never held (2 x 119 MB for a KITTI pair in float32; what the strips saved:
doc/notes/implementation_history.md).
On a GPU (`cuda.cnn.device_confidence`) the same strips are correlated in torch on the
device, as batched matrix products over blocks of columns.

Calibration: the raw cosine is high almost everywhere (most pixels score above 0.9), so a
threshold on it says little. The weights file carries a monotone map, fitted on validation
frames by the training tool, from the raw cosine to the probability that the CNN disparity
is within 1 px of the truth; `confidence` returns that probability, so theta = 0.6 keeps
the pixels whose CNN disparity is right with probability above 60 %. Weights without a map
give the raw cosine. The guided-filtered confidence (`cnn.filter`) has calibrations of its
own, one per radius, in the fits file beside the weights (`tools/fit_confidence.py`).
"""
import functools
from pathlib import Path
import time
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import nn
import torch.nn.functional as F

from . import filter as cnn_filter, int8 as cnn_int8
from .correlation import best_match, EPS, volume as correlation_volume
from .weights import cnn_calibrations, int8_entry, Knots, weights_path
from ..cancel import CancelFlag
from ..cost import check_max_disp
from ..images import gray_pair, standardize

PATCH = 9
FEATURES = 64
PAD = PATCH // 2
STRIP_ROWS = 64


class GcpNet(nn.Module):
    """Shared branch of the Siamese net: 9x9 patch -> 64-d L2-normalized descriptor."""

    def __init__(self) -> None:
        super().__init__()
        layers = []
        for i in range(4):
            layers += [nn.Conv2d(1 if i == 0 else FEATURES, FEATURES, 3), nn.ReLU()]
        self.branch = nn.Sequential(*layers)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """
        Apply the valid (unpadded) convolution to (N, 1, H, W).

        The result is L2-normalized, of shape (N, 64, H-8, W-8).
        """
        return F.normalize(self.branch(x).float(), dim=1, eps=EPS)

    def forward(self, left_patches: torch.Tensor, right_patches: torch.Tensor) -> torch.Tensor:
        """Confidences (N,) in [0, 1] of (N, 1, 9, 9) left/right patch pairs."""
        for name, p in (('left_patches', left_patches), ('right_patches', right_patches)):
            if p.ndim != 4 or tuple(p.shape[1:]) != (1, PATCH, PATCH):
                raise ValueError(f'{name} must have shape (N, 1, {PATCH}, {PATCH}), '
                                 f'got {tuple(p.shape)}')
        return (self.features(left_patches) * self.features(right_patches)).sum(dim=1).flatten()


def load_net(path: str | Path | None = None, device: str | torch.device = 'cpu') -> GcpNet:
    """
    Return a GcpNet in eval mode with the weights at `path` (default: the shipped weights).

    The file holds {'state_dict': ..., 'meta': {...}, 'calibration': ...} (see
    `gcp_stereo_ros.tools.train`); the calibrations of the guided-filtered confidence and
    the int8 entry (`net.int8`, None without one) are read from its side file
    (`weights.cnn_calibrations`, `weights.int8_entry`). Raises FileNotFoundError if it
    does not exist, ValueError if it cannot be read as such, holds NaN or infinite weights,
    or a calibration is invalid.
    """
    path = weights_path(path)
    if not path.is_file():
        raise FileNotFoundError(f'GCP CNN weights not found: {path}')
    try:
        blob = torch.load(path, map_location='cpu', weights_only=True)
        net = GcpNet()
        net.load_state_dict(blob['state_dict'])
    except Exception as e:  # any unreadable or mismatching file is reported the same way
        raise ValueError(f'GCP CNN weights file {path} is corrupt or not a GcpNet checkpoint: '
                         f'{e}') from e
    if not all(torch.isfinite(t).all() for t in net.state_dict().values()):
        raise ValueError(f'GCP CNN weights file {path} holds NaN or infinite weights '
                         '(a diverged training run?)')
    net.meta = blob.get('meta', {})
    net.path = path
    net.calibrations = cnn_calibrations(blob.get('calibration'), path)
    net.int8 = int8_entry(path)
    return net.to(device).eval()


def calibration(net: GcpNet, radius: int) -> Knots | None:
    """
    Return the net's calibration knots for confidences filtered with `radius` (0: none).

    The weights' own calibration serves 0 (None: the identity, weights without one); a
    calibration of each radius > 0 is fitted beside the weights (`tools/fit_confidence.py`),
    ValueError if there is none.
    """
    calibrations = getattr(net, 'calibrations', {0: None})
    if radius not in calibrations:
        where = getattr(net, 'path', 'the weights')
        raise ValueError(f'no calibration of the CNN confidence filtered with '
                         f'cnn_filter_radius {radius} beside {where}: '
                         f'fit one (python -m gcp_stereo_ros.tools.fit_confidence '
                         f'--cnn-filter-radius {radius}) or use cnn_filter_radius 0')
    return calibrations[radius]


def calibrated(net: GcpNet, cosine: np.ndarray | torch.Tensor, radius: int = 0
               ) -> np.ndarray | torch.Tensor:
    """
    Map raw confidences through the net's `calibration` for `radius`, as float32.

    `cosine`: a numpy array, or a tensor (mapped on its device as np.interp does, in float64);
    with `radius` the filtered maximum, on the cosine's scale.
    """
    knots = calibration(net, radius)
    if knots is None:
        return cosine
    if not isinstance(cosine, torch.Tensor):
        return np.interp(cosine, *knots).astype(np.float32)
    xp, fp = (torch.as_tensor(k, dtype=torch.float64, device=cosine.device) for k in knots)
    x = cosine.double()
    j = (torch.searchsorted(xp, x, right=True) - 1).clamp_(0, len(xp) - 2)
    y = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j]) * (x - xp[j]) + fp[j]
    return torch.where(x <= xp[0], fp[0], torch.where(x >= xp[-1], fp[-1], y)).float()


@functools.cache
def bf16_native(device: str | torch.device = 'cpu') -> bool:
    """
    Tell whether bfloat16 convolutions run natively on `device` (for precision 'auto').

    True on CUDA devices of compute capability 8.0 or more (Ampere on; torch emulates
    bfloat16 on older ones) and on CPUs with avx512_bf16 or AMX (`cnn.int8.cpu_flags`);
    elsewhere bfloat16 runs emulated, slower than float32.
    """
    device = torch.device(device)
    if device.type == 'cuda':
        return torch.cuda.is_available() and torch.cuda.get_device_capability(device)[0] >= 8
    return bool(cnn_int8.cpu_flags() & {'avx512_bf16', 'amx_bf16'})


def resolve_precision(precision: str, device: str | torch.device = 'cpu',
                      int8_fitted: bool = False) -> str:
    """
    Return the CNN's arithmetic for a `StereoConfig.precision`: 'int8', 'bf16' or 'fp32'.

    'auto' gives 'int8' on a CPU where `cnn.int8.int8_native` if the weights have an int8
    entry (`int8_fitted`: `weights.int8_entry`), else 'bf16' where `bf16_native(device)`,
    else 'fp32'; any other value is returned as it is.
    """
    if precision != 'auto':
        return precision
    if torch.device(device).type == 'cpu' and cnn_int8.int8_native() and int8_fitted:
        return 'int8'
    return 'bf16' if bf16_native(device) else 'fp32'


def network_input(*grays: np.ndarray) -> torch.Tensor:
    """Return what the branch sees of gray images, each standardized on its own."""
    return padded_input(torch.from_numpy(np.stack([standardize(g) for g in grays])))


def padded_input(x: torch.Tensor) -> torch.Tensor:
    """
    Return standardized images (N, H, W) as the branch takes them.

    That is one float32 batch (N, 1, H + 2 PAD, W + 2 PAD), replicate-padded by PAD so that
    every pixel gets a descriptor.
    """
    return F.pad(x[:, None], (PAD,) * 4, mode='replicate')


def descriptors(net: GcpNet, x: torch.Tensor, precision: str = 'fp32',
                cancel: CancelFlag | None = None) -> torch.Tensor:
    """
    Return the raw branch output (N, H, W, 64) of a padded input, on the input's device.

    The net runs in channels_last (the permute to (N, H, W, 64) is then free; its speed:
    doc/notes/implementation_history.md), each convolution with its ReLU (`_conv_relu`).
    `precision` (resolved, `resolve_precision`): 'fp32'; 'bf16', the first layer as
    `_first_layer_bf16` and the others in bfloat16 with float32 accumulation; 'int8' (CPU),
    the quantized branch (`cnn.int8.branch`), bfloat16 descriptors. `cancel`: a CancelFlag,
    checked before each layer (raises Cancelled).
    """
    if precision == 'int8':
        return cnn_int8.branch(net)(x, cancel)
    net.to(memory_format=torch.channels_last)  # in place; a 1-channel input cannot select it
    bf16 = precision == 'bf16'
    dtype = torch.bfloat16 if bf16 else torch.float32
    with torch.inference_mode():
        for i, conv in enumerate(net.branch[::2]):  # = net.branch(x), stoppable between layers
            if cancel is not None:
                cancel.check()
            if bf16 and i == 0:
                x = _first_layer_bf16(conv, x)
            else:
                x = _conv_relu(conv, x.to(dtype), conv.weight.to(dtype), conv.bias.to(dtype))
        return x.permute(0, 2, 3, 1)


def _conv_relu(conv: nn.Conv2d, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor
               ) -> torch.Tensor:
    """
    Return relu(conv2d(x, weight, bias)) with the geometry of `conv`.

    On the CPU as one oneDNN primitive, the ReLU applied to the output as it is written
    (no pass of its own over each layer's output; doc/notes/implementation_history.md).
    oneDNN's bfloat16 path needs avx512bw/vl/dq or avx_ne_convert:
    on other CPUs (AVX2 only) bfloat16 takes torch's plain convolution, emulated and slow
    (precision 'auto' does not pick it there).
    """
    if (x.device.type == 'cpu' and torch.backends.mkldnn.is_available()
            and (x.dtype != torch.bfloat16 or torch.ops.mkldnn._is_mkldnn_bf16_supported())):
        return torch.ops.mkldnn._convolution_pointwise(
            x, weight, bias, list(conv.padding), list(conv.stride), list(conv.dilation),
            conv.groups, 'relu', [], '')
    return F.relu(F.conv2d(x, weight, bias, stride=conv.stride, padding=conv.padding,
                           dilation=conv.dilation, groups=conv.groups), inplace=True)


def _first_layer_bf16(conv: nn.Conv2d, x: torch.Tensor) -> torch.Tensor:
    """
    Return relu(conv(x)) in bfloat16 with the accuracy of float32 input and weights.

    bfloat16 keeps 8 significant bits: rounding the standardized image to it is noise of
    the size of a gray level's step, different in the two images, which moves the error
    rates more than rounding the other layers does (the figures: doc/method.md, "bf16";
    doc/notes/implementation_history.md). So x = x_hi + x_lo and w = w_hi + w_lo, each part
    bfloat16, and
    x * w ~ x_hi w_hi + x_lo w_hi + x_hi w_lo (the dropped term is at most about 2^-16 of
    it): one bfloat16 convolution of 3 input channels, accumulated in float32, faster than
    the 1-channel float32 one.
    """
    def split(t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        hi = t.bfloat16()
        return hi, (t - hi.float()).bfloat16()

    (x_hi, x_lo), (w_hi, w_lo) = split(x), split(conv.weight.float())
    parts = torch.cat([x_hi, x_lo, x_hi], 1).contiguous(memory_format=torch.channels_last)
    weight = torch.cat([w_hi, w_hi, w_lo], 1).contiguous(memory_format=torch.channels_last)
    return _conv_relu(conv, parts, weight, conv.bias.bfloat16())


def confidence(net: GcpNet, left: npt.ArrayLike, right: npt.ArrayLike, max_disp: int,
               precision: str = 'fp32', volume: bool = False,
               seconds: dict[str, float] | None = None, cancel: CancelFlag | None = None,
               radius: int = 0, scratch: np.ndarray | None = None
               ) -> tuple[np.ndarray, ...]:
    """
    Return the CNN confidence of a rectified pair for disparities 0..max_disp-1, on the CPU.

    `left`/`right`: anything `images.gray_pair` accepts; each is standardized on its own.
    The convolutions run with torch (a CPU net), both images as one batch (see
    `descriptors`); `precision`: a `StereoConfig.precision` (`resolve_precision`). The L2
    normalization (float32) and the correlation run in a numba kernel, strip by strip,
    streaming over d without materializing the volume. With `radius` > 0 the volume of each
    strip is materialized and guided-filtered first (`cnn.filter.StripFilter`, in `scratch` if
    given). `seconds`: a dict that gains the wall time of the convolutions ('cnn') and of
    the correlation ('confidence'). `cancel`: a CancelFlag, checked before each layer of
    each strip (raises Cancelled). `cuda.cnn.device_confidence` is the GPU twin.

    Returns (cof_c, cof_d, cof_dr): float32 (H, W) max_d Vol in [0, 1] mapped through the
    net's calibration for `radius` (`calibrated`; the raw value without one), int32 (H, W)
    argmax_d Vol, where Vol(y, x, d) = 0 for x - d < 0 (with `radius` of the filtered
    volume), and int32 (H, W) cof_dr, for each right pixel xr the argmax of
    Vol(y, xr + d, d) over d < min(max_disp, W - xr) (always of the unfiltered volume);
    first maxima on ties. With `volume=True` also the float32 (H, W, max_disp) raw-cosine
    volume Vol, unfiltered (memory-hungry; for tests and plots).
    """
    lg, rg = gray_pair(left, right)
    h, w = lg.shape
    check_max_disp(max_disp, w)
    max_disp = int(max_disp)
    precision = resolve_precision(precision, 'cpu', getattr(net, 'int8', None) is not None)
    x = network_input(lg, rg)
    cof_c = np.empty((h, w), np.float32)
    cof_d = np.empty((h, w), np.int32)
    cof_dr = np.empty((h, w), np.int32)
    vol: Any = np.empty((h, w, max_disp), np.float32) if volume else None
    if radius:
        strips = cnn_filter.StripFilter(x[0, 0, PAD:PAD + h, PAD:PAD + w].numpy(), radius,
                                        max_disp, STRIP_ROWS, cof_c, cof_d, cof_dr, scratch)
    seconds = {} if seconds is None else seconds
    for stage in ('cnn', 'confidence'):
        seconds.setdefault(stage, 0.0)
    for y0 in range(0, h, STRIP_ROWS):
        y1 = min(y0 + STRIP_ROWS, h)
        t = time.perf_counter()
        f = descriptors(net, x[:, :, y0:y1 + 2 * PAD], precision, cancel).cpu().contiguous()
        if f.dtype == torch.bfloat16:  # the numba kernels widen and normalize it
            bits, shift = f.view(torch.int16).numpy().view(np.uint16), 16
        else:
            bits, shift = f.float().numpy().view(np.uint32), 0
        t1 = time.perf_counter()
        if radius:
            strips.add(bits, shift, y0)
        else:
            best_match(bits, shift, max_disp, cof_c[y0:y1], cof_d[y0:y1], cof_dr[y0:y1])
        if volume:
            correlation_volume(bits, shift, vol[y0:y1], 0, cof_dr[y0:y1])
        seconds['cnn'] += t1 - t
        seconds['confidence'] += time.perf_counter() - t1
    cof_c = calibrated(net, cof_c, radius)
    return (cof_c, cof_d, cof_dr, vol) if volume else (cof_c, cof_d, cof_dr)
