"""
The stages of the pipeline on a GPU (`StereoConfig.device` 'cuda[:N]'): `CudaBackend`.

Every array is a torch tensor on the device (`gpu`); the pair is uploaded once, the
volumes stay there and what is published comes back in one download. Each stage is the
CUDA twin beside its CPU stage (`cuda.cost`, `cuda.cnn`, `cuda.gcp`, `cuda.sgm`,
`cuda.disparity_confidence`, `cuda.postprocess`).
"""
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from . import cnn, cost, disparity_confidence, gcp, gpu, postprocess, sgm
from ..cancel import CancelFlag
from ..cnn.network import padded_input
from ..config import StereoConfig
from ..cost import max_cost
from ..costs import cost_spec
from ..disparity_confidence import ConfidenceFit
from ..stages import Buffers, CnnConfidence, CostVolume, KeptBuffers, Winners

CNN_TYPES = (np.float32, np.int32, np.int32)  # of cof_c, cof_d, cof_dr
ALIGN = 16  # bytes: where each array of a download starts


def standardize(pair: Any) -> Any:
    """
    Return `images.standardize` of each image of a float32 tensor (n, H, W), on its device.

    The mean and std summed in float64 (numpy's pairwise float32 sums give them within
    1e-6 relative), rounded to float32 for the arithmetic as numpy rounds them.
    """
    flat = pair.reshape(len(pair), -1).double()
    mean, std = flat.mean(1), flat.std(1, correction=0)
    std = torch.where(std > 1e-6, std, 1.0)  # a flat image
    return (pair - mean.float()[:, None, None]) / std.float()[:, None, None]


class CudaBackend(KeptBuffers):
    """The stages on the GPU `device` ('cuda' or 'cuda:N'); checked when made."""

    host = False

    def __init__(self, device: str) -> None:
        """Use `device`; ValueError unless numba-cuda and torch can both use it."""
        gpu.check_device(device)
        self.device = device
        super().__init__()
        self.torch_device = gpu.torch_device(device)

    def buffers(self, shape: tuple[int, ...], dtype: np.dtype, scratch: int) -> Buffers:
        """Return the kept volumes that fit (the GPU's CNN needs no scratch)."""
        vtype = gpu.VOLUME_TYPES[np.dtype(dtype)]
        return Buffers(self._fitting('cost', shape, vtype), self._fitting('total', shape, vtype),
                       None)

    def release(self) -> None:
        """Let go of the kept volumes (torch's caching allocator keeps their memory)."""
        self.kept.clear()

    def synchronize(self) -> None:
        """Wait for the GPU."""
        gpu.synchronize()

    def upload(self, left: np.ndarray, right: np.ndarray,
               standardized: bool) -> tuple[Any, Any]:
        """Return (pair, standardized pair or None), float32 tensors (2, H, W) on the GPU."""
        with gpu.current(self.device):
            pair = torch.from_numpy(np.stack([left, right])).to(self.torch_device)
            return pair, standardize(pair) if standardized else None

    def to_device(self, cnn: CnnConfidence) -> CnnConfidence:
        """Return host CNN outputs as tensors on the GPU."""
        return CnnConfidence(*(torch.from_numpy(np.ascontiguousarray(a, t)).to(self.torch_device)
                               for a, t in zip(cnn, CNN_TYPES)))

    def cnn_confidence(self, net: Any, pair: tuple[Any, Any], max_disp: int, precision: str,
                       radius: int, scratch: Any, seconds: dict[str, float] | None,
                       cancel: CancelFlag | None = None) -> CnnConfidence:
        """Return `cnn.device_confidence` of the standardized pair."""
        with gpu.current(self.device):
            return CnnConfidence(*cnn.device_confidence(
                net, padded_input(pair[1]), max_disp, precision, seconds, radius))

    def cost_volume(self, pair: tuple[Any, Any], max_disp: int, cost_name: str, window: int,
                    scale: int, dtype: np.dtype, out: Any,
                    cancel: CancelFlag | None = None) -> CostVolume:
        """Return `cuda.cost.cost_volume` of the gray or, as the cost says, standardized pair."""
        with gpu.current(self.device):
            costs = cost.cost_volume(pair[1] if cost_spec(cost_name).standardized else pair[0],
                                     max_disp, cost_name, window, out, scale, dtype)
        return CostVolume(costs, max_cost(cost_name, window) * scale)

    def select_refine(self, volume: CostVolume, cnn: CnnConfidence, theta: float, c_hi: float,
                      c_low: float, lr_check: bool, plain: Any) -> tuple[CostVolume, Any]:
        """Return the refined `volume` and the GCPs (`gcp.select_refine`)."""
        with gpu.current(self.device):
            gcps = gcp.select_refine(volume.costs, *cnn, theta, c_hi, c_low, lr_check, plain)
        return CostVolume(volume.costs, max(volume.top, c_hi)), gcps

    def aggregate(self, volume: CostVolume, p1: float, p2: float, paths: int, out: Any,
                  cancel: CancelFlag | None = None) -> Any:
        """Return `sgm.aggregate` of the volume into `out`."""
        with gpu.current(self.device):
            return sgm.aggregate(volume.costs, p1, p2, paths, volume.top, out)

    def disparity(self, total: Any, cancel: CancelFlag | None = None) -> Any:
        """Return `sgm.winners`' integer disparity."""
        with gpu.current(self.device):
            return sgm.winners(total)[0]

    def winners(self, total: Any, subpixel: bool, cancel: CancelFlag | None = None) -> Winners:
        """Return `sgm.winners` with the left-right agreement, and the margin."""
        with gpu.current(self.device):
            disp, consistent, s_best, s_second = sgm.winners(total, subpixel, True)
            return Winners(disp, consistent, disparity_confidence.margin(s_best, s_second))

    def median(self, disparity: Any) -> Any:
        """Return the 3x3 median of a (H, W) tensor, edges replicated as cv2.medianBlur."""
        padded = F.pad(disparity[None, None], (1, 1, 1, 1), mode='replicate')[0, 0]
        return padded.unfold(0, 3, 1).unfold(1, 3, 1).reshape(*disparity.shape, 9).median(2)[0]

    def disparity_confidence(self, fit: ConfidenceFit, winners: Winners,
                             cnn: CnnConfidence | None, gcps: Any) -> Any:
        """Return `disparity_confidence.calibrated` of its features."""
        cof_c, cof_d = (None, None) if cnn is None else cnn[:2]
        with gpu.current(self.device):
            planes = disparity_confidence.features(*winners, cof_c, cof_d, gcps)
            return disparity_confidence.calibrated(fit, planes)

    def invalidate(self, winners: Winners, confidence: Any, total: Any, plain: Any,
                   cfg: StereoConfig, camera: tuple[float, float] | None) -> tuple[Any, Any]:
        """Return `postprocess.invalidate` and the confidence, on the GPU."""
        with gpu.current(self.device):
            disp = postprocess.invalidate(*winners, cfg, camera, confidence, total, plain)
            if confidence is not None:
                confidence.masked_fill_(torch.isnan(disp), 0.0)
        return disp, confidence

    def to_host(self, *arrays: Any) -> tuple[np.ndarray | None, ...]:
        """Return tensors as numpy arrays: one download of them packed (None stays None)."""
        present = [a.contiguous() for a in arrays if a is not None]
        sizes = [a.numel() * a.element_size() for a in present]
        starts = np.cumsum([0] + [-(-n // ALIGN) * ALIGN for n in sizes])
        with gpu.current(self.device):
            packed = torch.empty(int(starts[-1]), dtype=torch.uint8,
                                 device=present[0].device if present else 'cpu')
            for a, start, n in zip(present, starts, sizes):
                packed[start:start + n] = a.view(-1).view(torch.uint8)
            host = packed.cpu().numpy()
        out = iter(host[start:start + n].view(torch.empty(0, dtype=a.dtype).numpy().dtype)
                   .reshape(a.shape) for a, start, n in zip(present, starts, sizes))
        return tuple(None if a is None else next(out) for a in arrays)
