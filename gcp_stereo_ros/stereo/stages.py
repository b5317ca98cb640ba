"""
The interface of the pipeline's stages: `Backend`, and the named types its stages return.

`StereoPipeline` runs the stages once, in order, over buffers it passes explicitly; a stage
returns arrays or a named type of them and never calls back. Two implementations:
`backend.CpuBackend` (numpy arrays, numba kernels, torch for the CNN) and
`cuda.backend.CudaBackend` (torch tensors on a GPU, numba-cuda kernels), with the same
results within float rounding (integer outputs and uint16 volumes bit-identical).
"""
from typing import Any, NamedTuple, Protocol

import numpy as np

from .cancel import CancelFlag
from .config import StereoConfig
from .disparity_confidence import ConfidenceFit

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
    scratch: Array | None  # float32 rows of the CPU's CNN filter (`cnn.filter.StripFilter`)


class KeptBuffers:
    """The buffers a backend keeps from one pair for the next, by name; both backends'."""

    def __init__(self) -> None:
        """Start with none kept."""
        self.kept: dict[str, Array] = {}

    def _fitting(self, name: str, shape: tuple[int, ...], dtype: Any) -> Array | None:
        """Return the kept buffer `name` if it has `shape` and `dtype`; else let it go."""
        a = self.kept.pop(name, None)
        if a is not None and tuple(a.shape) == shape and a.dtype == dtype:
            self.kept[name] = a
            return a
        return None

    def keep(self, buffers: Buffers) -> None:
        """Keep the buffers that are not None."""
        self.kept.update((k, v) for k, v in buffers._asdict().items() if v is not None)


class Backend(Protocol):
    """
    The stages of `StereoPipeline` on one device, in the order it runs them.

    Arrays are the backend's own (`Array`); `upload` and `to_host` cross to and from numpy.
    `cancel`: a CancelFlag that CPU kernels check (raising Cancelled); a GPU ignores it.
    """

    host: bool  # True: the stages run on the host, there is nothing to upload or download
    torch_device: Any  # where the CNN runs: 'cpu' or a torch.device

    def buffers(self, shape: tuple[int, ...], dtype: np.dtype, scratch: int) -> Buffers:
        """Return the kept buffers for volumes `shape` of `dtype`, letting go the others."""

    def keep(self, buffers: Buffers) -> None:
        """Keep `buffers` for the next pair."""

    def release(self) -> None:
        """Let go of every kept buffer."""

    def synchronize(self) -> None:
        """Wait for the device's work so far (for timing its stages)."""

    def upload(self, left: np.ndarray, right: np.ndarray, standardized: bool) -> Any:
        """Return the gray float32 pair (H, W) on the device, with `standardized` copies."""

    def to_device(self, cnn: CnnConfidence) -> CnnConfidence:
        """Return host CNN outputs on the device."""

    def cnn_confidence(self, net: Any, pair: Any, max_disp: int, precision: str, radius: int,
                       scratch: Array | None, seconds: dict[str, float] | None,
                       cancel: CancelFlag | None = None) -> CnnConfidence:
        """
        Return the CNN confidence of the pair.

        `seconds` gains 'cnn' and 'confidence' (a GPU waits for them; None: not timed).
        """

    def cost_volume(self, pair: Any, max_disp: int, cost: str, window: int, scale: int,
                    dtype: np.dtype, out: Array | None,
                    cancel: CancelFlag | None = None) -> CostVolume:
        """Return the matching cost volume (`cost.cost_volume`), into `out` if not None."""

    def select_refine(self, volume: CostVolume, cnn: CnnConfidence, theta: float,
                      c_hi: float, c_low: float, lr_check: bool,
                      plain: Array | None) -> tuple[CostVolume, Array]:
        """Refine `volume` in place by the GCPs `gcp.select` picks; return it and the GCPs."""

    def aggregate(self, volume: CostVolume, p1: float, p2: float, paths: int,
                  out: Array | None, cancel: CancelFlag | None = None) -> Array:
        """Return the summed SGM path costs of `volume` (`sgm.aggregate`) into `out`."""

    def disparity(self, total: Array, cancel: CancelFlag | None = None) -> Array:
        """Return the integer winner-takes-all disparity of summed costs, float32 (H, W)."""

    def winners(self, total: Array, subpixel: bool, cancel: CancelFlag | None = None) -> Winners:
        """Return the winners of summed costs, with the left-right agreement and margin."""

    def median(self, disparity: Array) -> Array:
        """Return the 3x3 median of the disparity, as cv2.medianBlur."""

    def disparity_confidence(self, fit: ConfidenceFit, winners: Winners,
                             cnn: CnnConfidence | None, gcp: Array | None) -> Array:
        """Return the disparity confidence (`disparity_confidence.features`, then `fit`)."""

    def invalidate(self, winners: Winners, confidence: Array | None, total: Array,
                   plain: Array | None, cfg: StereoConfig,
                   camera: tuple[float, float] | None) -> tuple[Array, Array | None]:
        """
        Return the disparity invalidated (`postprocess.invalidate`) and the confidence.

        Both in place: the winners' disparity NaN where cfg's tests fail (`total`: the
        summed costs for the background test; `plain`: plain SGM's disparity or None;
        `camera`: as `StereoPipeline.__call__` takes it), the confidence (None stays None)
        0 there.
        """

    def to_host(self, *arrays: Array | None) -> tuple[np.ndarray | None, ...]:
        """Return the arrays as numpy arrays, in one download (None stays None)."""
