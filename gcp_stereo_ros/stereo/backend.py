"""
The pipeline's stages on the CPU (`CpuBackend`), and the backend of a device (`backend`).

`backend(device)` returns the `stages.Backend` of a `StereoConfig.device`: this module's
`CpuBackend`, or `backend_cuda.CudaBackend` on a GPU.
"""
from functools import partial

import cv2
import numpy as np

from . import cost, gcp, sgm
from .disparity_confidence import features, margin
from .images import gray_pair
from .memory import call_glibc
from .postprocess import invalidate
from .stages import Backend, Buffers, CnnConfidence, CostVolume, Winners


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

    def invalidate(self, winners, confidence, total, plain, cfg, camera):
        """Return `postprocess.invalidate` (costs by `sgm.costs_at`) and the confidence."""
        disp = invalidate(*winners, cfg, camera, confidence, partial(sgm.costs_at, total), plain)
        if confidence is not None:
            confidence[np.isnan(disp)] = 0.0
        return disp, confidence

    def to_host(self, *arrays):
        """Return the arrays themselves."""
        return arrays


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
    return CnnConfidence(*b.to_host(*cnn))
