"""
The pipeline's stages on the CPU (`CpuBackend`), and the backend of a device (`backend`).

`backend(device)` returns the `stages.Backend` of a `StereoConfig.device`: this module's
`CpuBackend`, or `cuda.backend.CudaBackend` on a GPU.
"""
from functools import partial
from typing import Any

import cv2
import numpy as np

from . import cost, gcp, sgm
from .cancel import CancelFlag
from .config import StereoConfig
from .disparity_confidence import ConfidenceFit, features, margin
from .images import gray_pair
from .memory import call_glibc
from .postprocess import invalidate
from .stages import Backend, Buffers, CnnConfidence, CostVolume, KeptBuffers, Winners


class CpuBackend(KeptBuffers):
    """The stages on the CPU: numba kernels (threads: numba's), torch for the CNN."""

    host = True
    torch_device: Any = 'cpu'

    def buffers(self, shape: tuple[int, ...], dtype: np.dtype, scratch: int) -> Buffers:
        """Return the kept buffers that fit, letting go of the others first."""
        cost_, total = (self._fitting(name, shape, dtype) for name in ('cost', 'total'))
        rows = self._fitting('scratch', (scratch,), np.float32)
        if scratch and rows is None:
            rows = np.empty(scratch, np.float32)
        return Buffers(cost_, total, rows if scratch else None)

    def release(self) -> None:
        """Let go of the kept buffers, and of the heap blocks they were."""
        self.kept.clear()
        call_glibc('malloc_trim', 0)

    def synchronize(self) -> None:
        """Nothing to wait for: the CPU's stages return when done."""

    def upload(self, left: np.ndarray, right: np.ndarray,
               standardized: bool) -> tuple[np.ndarray, np.ndarray]:
        """Return the gray pair itself: the CPU stages standardize where they need to."""
        return left, right

    def to_device(self, cnn: CnnConfidence) -> CnnConfidence:
        """Return `cnn` itself."""
        return cnn

    def cnn_confidence(self, net: Any, pair: tuple[np.ndarray, np.ndarray], max_disp: int,
                       precision: str, radius: int, scratch: np.ndarray | None,
                       seconds: dict[str, float] | None,
                       cancel: CancelFlag | None = None) -> CnnConfidence:
        """Return `cnn.confidence` (torch is imported with the CNN)."""
        from .cnn.network import confidence
        return CnnConfidence(*confidence(net, *pair, max_disp, precision, seconds=seconds,
                                         cancel=cancel, radius=radius, scratch=scratch))

    def cost_volume(self, pair: tuple[np.ndarray, np.ndarray], max_disp: int, cost_name: str,
                    window: int, scale: int, dtype: np.dtype, out: np.ndarray | None,
                    cancel: CancelFlag | None = None) -> CostVolume:
        """Return `cost.cost_volume` of the pair into `out`."""
        costs = cost.cost_volume(*pair, max_disp, cost_name, window, out, scale, dtype, cancel)
        return CostVolume(costs, cost.max_cost(cost_name, window) * scale)

    def select_refine(self, volume: CostVolume, cnn: CnnConfidence, theta: float, c_hi: float,
                      c_low: float, lr_check: bool,
                      plain: np.ndarray | None) -> tuple[CostVolume, np.ndarray]:
        """Return the refined `volume` and the GCPs (`gcp.select`, `gcp.refine`)."""
        gcps = gcp.select(*cnn, theta, lr_check, plain)
        gcp.refine(volume.costs, gcps, cnn.cof_d, c_hi, c_low)
        return CostVolume(volume.costs, max(volume.top, c_hi)), gcps

    def aggregate(self, volume: CostVolume, p1: float, p2: float, paths: int,
                  out: np.ndarray | None, cancel: CancelFlag | None = None) -> np.ndarray:
        """Return `sgm.aggregate` of the volume into `out`."""
        return sgm.aggregate(volume.costs, p1, p2, paths, out, cancel)

    def disparity(self, total: np.ndarray, cancel: CancelFlag | None = None) -> np.ndarray:
        """Return `sgm.winners`' integer disparity."""
        return sgm.winners(total, False, False, cancel)[0]

    def winners(self, total: np.ndarray, subpixel: bool,
                cancel: CancelFlag | None = None) -> Winners:
        """Return `sgm.winners` with the left-right agreement, and the margin."""
        disp, consistent, s_best, s_second = sgm.winners(total, subpixel, True, cancel)
        return Winners(disp, consistent, margin(s_best, s_second))

    def median(self, disparity: np.ndarray) -> np.ndarray:
        """Return cv2.medianBlur(disparity, 3)."""
        return cv2.medianBlur(disparity, 3)

    def disparity_confidence(self, fit: ConfidenceFit, winners: Winners,
                             cnn: CnnConfidence | None, gcps: np.ndarray | None) -> np.ndarray:
        """Return `fit` of `disparity_confidence.features`."""
        cof_c, cof_d = (None, None) if cnn is None else cnn[:2]
        return fit(features(*winners, cof_c, cof_d, gcps))

    def invalidate(self, winners: Winners, confidence: np.ndarray | None, total: np.ndarray,
                   plain: np.ndarray | None, cfg: StereoConfig,
                   camera: tuple[float, float] | None
                   ) -> tuple[np.ndarray, np.ndarray | None]:
        """Return `postprocess.invalidate` (costs by `sgm.costs_at`) and the confidence."""
        disp = invalidate(*winners, cfg, camera, confidence, partial(sgm.costs_at, total), plain)
        if confidence is not None:
            confidence[np.isnan(disp)] = 0.0
        return disp, confidence

    def to_host(self, *arrays: np.ndarray | None) -> tuple[np.ndarray | None, ...]:
        """Return the arrays themselves."""
        return arrays


def backend(device: str) -> Backend:
    """
    Return a fresh backend for a `StereoConfig.device`: 'cpu', or 'cuda[:N]'.

    ValueError if the GPU cannot be used (`gpu.check_device`), naming why.
    """
    if device == 'cpu':
        return CpuBackend()
    from .cuda.backend import CudaBackend  # numba-cuda is an optional dependency
    return CudaBackend(device)


def cnn_confidence(net: Any, left: np.ndarray, right: np.ndarray, max_disp: int,
                   device: str = 'cpu', precision: str = 'fp32',
                   radius: int = 0) -> CnnConfidence:
    """
    Return the host `CnnConfidence` of a pair on `device`: the CNN alone, for the tools.

    `net` on that device (`StereoPipeline.net`); `left`, `right`: anything
    `images.gray_pair` takes.
    """
    b = backend(device)
    left, right = gray_pair(left, right)
    pair = b.upload(left, right, True)
    cnn = b.cnn_confidence(net, pair, max_disp, precision, radius, None, None)
    return CnnConfidence(*b.to_host(*cnn))
