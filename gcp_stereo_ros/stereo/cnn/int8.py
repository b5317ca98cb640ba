"""
int8 CNN descriptors on the CPU: post-training quantization of the branch (`cnn.GcpNet`).

The first layer (1 to 64 maps, 1.6 % of the branch's work) runs in a numba kernel that sums
in float32 and writes its ReLU output rounded to uint8 steps (`_first_layer`). Layers 2-4
run as oneDNN int8 convolutions (`torch.ops.onednn.qconv2d_pointwise`: uint8 activations, int8
weights with one scale per output map, int32 sums, bias and ReLU applied as the output is
written; twice the bfloat16 rate on CPUs with AVX512-VNNI or AMX). Layers 2 and 3 write
uint8, the last writes bfloat16 descriptors, which the correlation reads as bf16 ones.

The maps of one layer differ in range by up to 200x, and one uint8 scale serves them all, so
each map k of layers 1-3 is first divided by its range r_k (the 99.99th percentile of its
activations on the training frames: the layer's weights and bias divided by r_k, the next
layer's weights of that input map multiplied by it, the same function since ReLU commutes
with positive scales); each layer's uint8 step is then the 99.95th percentile of the
scaled activations / 255 (larger values clip). The ranges and clips are fitted by
`fit` on training frames and stored in the side file beside the weights (under
`weights.INT8_KEY`; `tools/fit_confidence.py --int8`). What it costs in accuracy and gains in
speed: doc/method.md, "int8".
"""
from collections.abc import Iterable
import functools
from pathlib import Path
from typing import Any

from numba import njit, prange
import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F

from ..cancel import CancelFlag


CHANNEL_PERCENTILE = 99.99  # a map's range r_k
CLIP_PERCENTILE = 99.95  # a layer's clip, of the activations divided by their ranges
LEVELS = 255  # uint8 steps of an activation
SAMPLES = 5000  # activations sampled of each layer per frame for `fit`
_ONE, _ZERO = [1, 1], [0, 0]


def int8_available() -> bool:
    """Tell whether this torch has oneDNN's int8 convolution (x86 CPUs)."""
    return (torch.backends.mkldnn.is_available()
            and hasattr(torch.ops.onednn, 'qconv2d_pointwise'))


@functools.cache
def cpu_flags() -> frozenset[str]:
    """Return the CPU's feature flags as /proc/cpuinfo names them (empty where unreadable)."""
    try:
        return frozenset(Path('/proc/cpuinfo').read_text().split())
    except OSError:
        return frozenset()


def int8_native() -> bool:
    """
    Tell whether int8 convolutions run at their fast rate here (what precision 'auto' uses).

    True on CPUs with AVX512-VNNI, AVX-VNNI or AMX-INT8 (`cpu_flags`) when this torch has
    oneDNN's int8 convolution.
    """
    return int8_available() and bool(cpu_flags() & {'avx512_vnni', 'avx_vnni', 'amx_int8'})


class Int8Branch:
    """
    The branch of a GcpNet quantized with per-map `ranges` (3, 64) and layer `clips` (3,).

    Calling it on a padded input (N, 1, H + 8, W + 8) float32 returns the raw descriptors
    (N, H, W, 64) bfloat16, as `cnn.descriptors` does in bf16.
    """

    def __init__(self, net: Any, ranges: Any, clips: Iterable[float]) -> None:
        ranges = torch.as_tensor(np.asarray(ranges, np.float32))
        clips = [float(c) for c in clips]
        convs = list(net.branch[::2])
        if ranges.shape != (3, convs[0].out_channels) or len(clips) != 3:
            raise ValueError(f'int8 ranges must be (3, {convs[0].out_channels}) and clips 3, '
                             f'got {tuple(ranges.shape)} and {len(clips)}')
        if not (torch.isfinite(ranges).all() and (ranges > 0).all()
                and all(np.isfinite(c) and c > 0 for c in clips)):
            raise ValueError('int8 ranges and clips must be finite and positive')
        weights = [c.weight.detach().float().clone() for c in convs]
        biases = [c.bias.detach().float().clone() for c in convs]
        for i, r in enumerate(ranges):  # map k of layer i divided by r_k
            weights[i] /= r[:, None, None, None]
            biases[i] /= r
            weights[i + 1] *= r[None, :, None, None]
        self.steps = [c / LEVELS for c in clips]  # uint8 step of layers 1-3's outputs
        # layer 1 (`_first_layer`) sums in steps, + 0.5 so that truncation rounds
        self.weight1 = (weights[0][:, 0] / self.steps[0]).permute(1, 2, 0).contiguous().numpy()
        self.bias1 = (biases[0] / self.steps[0] + 0.5).numpy()
        self.layers = []
        for i, (w, b) in enumerate(zip(weights[1:], biases[1:])):
            scale = (w.abs().amax((1, 2, 3)) / 127).clamp_min(torch.finfo(torch.float32).tiny)
            q = torch.round(w / scale[:, None, None, None]).clamp(-127, 127).to(torch.int8)
            packed = torch.ops.onednn.qconv_prepack(q, scale, self.steps[i], 0, _ONE, _ZERO,
                                                    _ONE, 1, None)
            self.layers.append((packed, scale, torch.zeros(len(scale), dtype=torch.int64), b))

    def __call__(self, x: torch.Tensor, cancel: CancelFlag | None = None) -> torch.Tensor:
        with torch.inference_mode():
            if cancel is not None:
                cancel.check()
            n, _, h, w = x.shape
            first = np.empty((n, h - 2, w - 2, len(self.bias1)), np.uint8)
            _first_layer(np.ascontiguousarray(x[:, 0].numpy()), self.weight1, self.bias1, first)
            q = torch.from_numpy(first).permute(0, 3, 1, 2)  # channels_last (N, 64, H, W)
            for i, (packed, scale, zero, bias) in enumerate(self.layers):
                if cancel is not None:
                    cancel.check()
                last = i == len(self.layers) - 1
                q = torch.ops.onednn.qconv2d_pointwise(
                    q, self.steps[i], 0, packed, scale, zero, bias, _ONE, _ZERO, _ONE, 1,
                    1.0 if last else self.steps[i + 1], 0, torch.bfloat16 if last else None,
                    'relu', [], '')
            return q.permute(0, 2, 3, 1)


@njit(parallel=True, cache=True, fastmath=True, nogil=True)
def _first_layer(x: np.ndarray, w: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """
    Write the first layer's uint8 output: trunc(clamp(conv(x, w) + b, 0, 255)).

    x: (N, H + 2, W + 2) float32 input, w: (3, 3, C) float32 weights, b: (C,) bias, out:
    (N, H, W, C) uint8. Sums in float32, as the float32 convolution does.
    """
    n, h, width, c = out.shape
    for t in prange(n * h):
        i, y = t // h, t % h
        acc = np.empty(c, np.float32)
        for x0 in range(width):
            acc[:] = b
            for dy in range(3):
                for dx in range(3):
                    v = x[i, y + dy, x0 + dx]
                    for k in range(c):
                        acc[k] += v * w[dy, dx, k]
            for k in range(c):
                out[i, y, x0, k] = np.uint8(min(max(acc[k], np.float32(0.0)),
                                                np.float32(LEVELS)))


def branch(net: Any) -> Int8Branch:
    """
    Return the net's Int8Branch, made once from its int8 entry (`cnn.load_net`'s `net.int8`).

    ValueError if the net has no such entry (fit one: tools/fit_confidence.py --int8), it is
    invalid, or this torch cannot run int8 convolutions.
    """
    made = getattr(net, 'int8_branch', None)
    if made is not None:
        return made
    if not int8_available():
        raise ValueError('precision int8 needs torch with oneDNN int8 convolutions (x86 CPU)')
    where = getattr(net, 'path', 'the weights')
    entry = getattr(net, 'int8', None)
    if entry is None:
        raise ValueError(f'no int8 activation ranges beside {where}: fit them '
                         '(python -m gcp_stereo_ros.tools.fit_confidence --int8 ...) or use '
                         'another precision')
    try:
        net.int8_branch = Int8Branch(net, entry['ranges'], entry['clips'])
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f'{where}: invalid int8 entry: {err}') from None
    return net.int8_branch


def fit(net: Any, inputs: Iterable[torch.Tensor], names: Iterable[str]) -> dict[str, Any]:
    """
    Return the int8 entry {'ranges', 'clips', 'frames'} fitted on training frames.

    `inputs`: each frame's padded network input (N, 1, H + 8, W + 8), as `cnn.network_input`
    makes it; `names`: the frames' names. `SAMPLES` activations of each layer per frame
    (seeded: the same frames give the same entry).
    """
    rng = np.random.default_rng(0)
    acts = np.concatenate([_samples(net, x, SAMPLES, rng) for x in inputs], axis=1)  # (3, n, 64)
    ranges = np.percentile(acts, CHANNEL_PERCENTILE, axis=1)
    ranges = np.where(ranges > 0, ranges, acts.max(axis=1))  # a map zero that often: its max
    ranges = np.where(ranges > 0, ranges, 1.0)  # a map never active: any scale
    clips = [float(np.percentile(a / r, CLIP_PERCENTILE)) for a, r in zip(acts, ranges)]
    return {'ranges': ranges.tolist(), 'clips': clips, 'frames': list(names)}


def _samples(net: Any, x: torch.Tensor, count: int, rng: np.random.Generator
             ) -> npt.NDArray[np.float32]:
    """Return (3, count, 64) float32: layers 1-3's float32 outputs at `count` random pixels."""
    out = []
    with torch.inference_mode():
        a = x
        for conv in list(net.branch[::2])[:3]:
            a = F.relu(F.conv2d(a, conv.weight, conv.bias))
            flat = a.permute(0, 2, 3, 1).reshape(-1, a.shape[1])
            out.append(flat[torch.from_numpy(rng.integers(0, len(flat), count))].numpy())
    return np.stack(out)
