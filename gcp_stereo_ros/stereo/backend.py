"""
The stages of the pipeline as one interface, `Backend`, and its CPU implementation.

`StereoPipeline` runs the stages once, in order, over buffers it passes explicitly; a stage
returns arrays or a named type of them and never calls back. Two implementations:
`CpuBackend` (numpy arrays, numba kernels, torch for the CNN) and `backend_cuda.CudaBackend`
(torch tensors on a GPU, numba-cuda kernels), with the same results within float rounding
(integer outputs and uint16 volumes bit-identical). `backend(device)` returns the one for a
`StereoConfig.device`.
"""
from typing import Any, NamedTuple, Protocol

import cv2
import numpy as np

from . import cost, gcp, sgm
from .disparity_confidence import ConfidenceFit, features, margin
from .images import gray_pair
from .memory import call_glibc

Array = Any  # a numpy array on the CPU, a torch tensor on a GPU


class CnnConfidence(NamedTuple):
    """The CNN's outputs for a pair, each (H, W) (`cnn.confidence`)."""

    cof_c: Array  # float32 in [0, 1]: the calibrated CNN confidence of cof_d
    cof_d: Array  # int32 px: the CNN's best disparity
    cof_dr: Array  # int32 px: the right view's best disparity at each right pixel


class CostVolume(NamedTuple):
    """A cost volume (H, W, D), float32 or uint16 fixed point, and its largest cost."""

    costs: Array
    top: float


class Winners(NamedTuple):
    """The winner-takes-all of summed costs, each (H, W) (`sgm.winners`)."""

    disparity: Array  # float32 px, sub-pixel with `subpixel`
    consistent: Array  # bool: the right view's winner at x - d is within 1 px of d
    margin: Array  # float32 in [0, 1]: 1 - S(winner) / S(rival) (`disparity_confidence.margin`)


class Buffers(NamedTuple):
    """Arrays kept from the previous pair for the next, None where none fits."""

    cost: Array | None  # the cost volume
    total: Array | None  # the summed path costs
    scratch: Array | None  # float32 rows of the CPU's CNN filter (`cnn_filter.StripFilter`)


class Backend(Protocol):
    """
    The stages of `StereoPipeline` on one device, in the order it runs them.

    Arrays are the backend's own (`Array`); `upload` and `to_host` cross to and from numpy.
    `cancel`: a CancelFlag that CPU kernels check (raising Cancelled); a GPU ignores it.
    """

    host: bool  # True: the stages run on the host, there is nothing to upload or download
    torch_device: Any  # where the CNN runs: 'cpu' or a torch.device

    def buffers(self, shape: tuple, dtype: np.dtype, scratch: int) -> Buffers:
        """Return the kept buffers for volumes `shape` of `dtype`, letting go the others."""

    def keep(self, buffers: Buffers) -> None:
        """Keep `buffers` for the next pair."""

    def release(self) -> None:
        """Let go of every kept buffer."""

    def synchronize(self) -> None:
        """Wait for the device's work so far (for stage timings)."""

    def upload(self, left: np.ndarray, right: np.ndarray, standardized: bool) -> Any:
        """Return the gray float32 pair (H, W) on the device, with `standardized` copies."""

    def to_device(self, cnn: CnnConfidence) -> CnnConfidence:
        """Return host CNN outputs on the device."""

    def cnn_confidence(self, net, pair, max_disp: int, bf16, radius: int, scratch,
                       seconds: dict, cancel=None) -> CnnConfidence:
        """Return the CNN confidence of the pair; `seconds` gains 'cnn' and 'confidence'."""

    def cost_volume(self, pair, max_disp: int, cost: str, window: int, scale: int,
                    dtype: np.dtype, out, cancel=None) -> CostVolume:
        """Return the matching cost volume (`cost.cost_volume`), into `out` if not None."""

    def select_refine(self, volume: CostVolume, cnn: CnnConfidence, theta: float,
                      c_hi: float, c_low: float, lr_check: bool,
                      plain) -> tuple[CostVolume, Array]:
        """Refine `volume` in place by the GCPs `gcp.select` picks; return it and the GCPs."""

    def aggregate(self, volume: CostVolume, p1: float, p2: float, paths: int, out,
                  cancel=None) -> Array:
        """Return the summed SGM path costs of `volume` (`sgm.aggregate`) into `out`."""

    def disparity(self, total, cancel=None) -> Array:
        """Return the integer winner-takes-all disparity of summed costs, float32 (H, W)."""

    def winners(self, total, subpixel: bool, cancel=None) -> Winners:
        """Return the winners of summed costs, with the left-right agreement and margin."""

    def median(self, disparity) -> Array:
        """Return the 3x3 median of the disparity, as cv2.medianBlur."""

    def disparity_confidence(self, fit: ConfidenceFit, winners: Winners,
                             cnn: CnnConfidence | None, gcp) -> Array:
        """Return the disparity confidence (`disparity_confidence.features`, then `fit`)."""

    def to_host(self, array) -> np.ndarray | None:
        """Return `array` as a numpy array (None stays None)."""

    def costs_at(self, total, rows: np.ndarray, cols: np.ndarray,
                 disparities: np.ndarray) -> np.ndarray:
        """Return total[rows[i], cols[i], disparities[i, j]] on the host, (n, k)."""


class CpuBackend:
    """The stages on the CPU: numba kernels (threads: numba's), torch for the CNN."""

    host = True
    torch_device = 'cpu'

    def __init__(self):
        """Start with no kept buffers."""
        self.kept: dict[str, np.ndarray] = {}

    def _fitting(self, name, shape, dtype):
        """Return the kept array `name` if it has `shape` and `dtype`; else let it go."""
        a = self.kept.pop(name, None)
        if a is not None and a.shape == shape and a.dtype == dtype:
            self.kept[name] = a
            return a
        return None

    def buffers(self, shape, dtype, scratch):
        """Return the kept buffers that fit, letting go of the others first."""
        cost_, total = (self._fitting(name, shape, dtype) for name in ('cost', 'total'))
        rows = self._fitting('scratch', (scratch,), np.float32)
        if scratch and rows is None:
            rows = np.empty(scratch, np.float32)
        return Buffers(cost_, total, rows if scratch else None)

    def keep(self, buffers):
        """Keep the buffers that are not None."""
        self.kept.update((k, v) for k, v in buffers._asdict().items() if v is not None)

    def release(self):
        """Let go of the kept buffers, and of the heap blocks they were."""
        self.kept.clear()
        call_glibc('malloc_trim', 0)

    def synchronize(self):
        """Nothing to wait for: the CPU's stages return when done."""

    def upload(self, left, right, standardized):
        """Return the gray pair itself: the CPU stages standardize where they need to."""
        return left, right

    def to_device(self, cnn):
        """Return `cnn` itself."""
        return cnn

    def cnn_confidence(self, net, pair, max_disp, bf16, radius, scratch, seconds, cancel=None):
        """Return `cnn.confidence` (torch is imported with the CNN)."""
        from .cnn import confidence
        return CnnConfidence(*confidence(net, *pair, max_disp, bf16, seconds=seconds,
                                         cancel=cancel, radius=radius, scratch=scratch))

    def cost_volume(self, pair, max_disp, cost_name, window, scale, dtype, out, cancel=None):
        """Return `cost.cost_volume` of the pair into `out`."""
        costs = cost.cost_volume(*pair, max_disp, cost_name, window, out, scale, dtype, cancel)
        return CostVolume(costs, cost.max_cost(cost_name, window) * scale)

    def select_refine(self, volume, cnn, theta, c_hi, c_low, lr_check, plain):
        """Return the refined `volume` and the GCPs (`gcp.select`, `gcp.refine`)."""
        gcps = gcp.select(*cnn, theta, lr_check, plain)
        gcp.refine(volume.costs, gcps, cnn.cof_d, c_hi, c_low)
        return CostVolume(volume.costs, max(volume.top, c_hi)), gcps

    def aggregate(self, volume, p1, p2, paths, out, cancel=None):
        """Return `sgm.aggregate` of the volume into `out`."""
        return sgm.aggregate(volume.costs, p1, p2, paths, out, cancel)

    def disparity(self, total, cancel=None):
        """Return `sgm.winners`' integer disparity."""
        return sgm.winners(total, False, False, cancel)[0]

    def winners(self, total, subpixel, cancel=None):
        """Return `sgm.winners` with the left-right agreement, and the margin."""
        disp, consistent, s_best, s_second = sgm.winners(total, subpixel, True, cancel)
        return Winners(disp, consistent, margin(s_best, s_second))

    def median(self, disparity):
        """Return cv2.medianBlur(disparity, 3)."""
        return cv2.medianBlur(disparity, 3)

    def disparity_confidence(self, fit, winners, cnn, gcps):
        """Return `fit` of `disparity_confidence.features`."""
        cof_c, cof_d = (None, None) if cnn is None else cnn[:2]
        return fit(features(*winners, cof_c, cof_d, gcps))

    def to_host(self, array):
        """Return `array` itself."""
        return array

    def costs_at(self, total, rows, cols, disparities):
        """Return `sgm.costs_at`."""
        return sgm.costs_at(total, rows, cols, disparities)


def backend(device: str) -> Backend:
    """
    Return a fresh backend for a `StereoConfig.device`: 'cpu', or 'cuda[:N]'.

    ValueError if the GPU cannot be used (`gpu.check_device`), naming why.
    """
    if device == 'cpu':
        return CpuBackend()
    from .backend_cuda import CudaBackend  # numba-cuda is an optional dependency
    return CudaBackend(device)


def cnn_confidence(net, left, right, max_disp, device='cpu', bf16=False, radius=0):
    """
    Return the host `CnnConfidence` of a pair on `device`: the CNN alone, for the tools.

    `net` on that device (`StereoPipeline.net`); `left`, `right`: anything
    `images.gray_pair` takes.
    """
    b = backend(device)
    pair = b.upload(*gray_pair(left, right), True)
    cnn = b.cnn_confidence(net, pair, max_disp, bf16, radius, None, {})
    return CnnConfidence(*(b.to_host(a) for a in cnn))
