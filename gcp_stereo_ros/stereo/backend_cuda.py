"""
The stages of the pipeline on a GPU (`StereoConfig.device` 'cuda[:N]'): `CudaBackend`.

Every array is a torch tensor on the device (`gpu`); the pair is uploaded once and the
volumes stay there. Each stage is the CUDA twin beside its CPU stage (`cost_cuda`,
`cnn_cuda`, `gcp_cuda`, `sgm_cuda`, `disparity_confidence_cuda`).
"""
import numpy as np
import torch
import torch.nn.functional as F

from . import cnn_cuda, cost_cuda, disparity_confidence_cuda, gcp_cuda, gpu, sgm_cuda
from .cnn import padded_input
from .cost import max_cost
from .images import mean_std
from .stages import Buffers, CnnConfidence, CostVolume, Winners

CNN_TYPES = (np.float32, np.int32, np.int32)  # of cof_c, cof_d, cof_dr


class CudaBackend:
    """The stages on the GPU `device` ('cuda' or 'cuda:N'); checked when made."""

    host = False

    def __init__(self, device):
        """Use `device`; ValueError unless numba-cuda and torch can both use it."""
        gpu.check_device(device)
        self.device = device
        self.torch_device = gpu.torch_device(device)
        self.kept: dict[str, torch.Tensor] = {}

    def _fitting(self, name, shape, dtype):
        a = self.kept.pop(name, None)
        if a is not None and tuple(a.shape) == shape and a.dtype == dtype:
            self.kept[name] = a
            return a
        return None

    def buffers(self, shape, dtype, scratch):
        """Return the kept volumes that fit (the GPU's CNN needs no scratch)."""
        vtype = gpu.VOLUME_TYPES[np.dtype(dtype)]
        return Buffers(self._fitting('cost', shape, vtype), self._fitting('total', shape, vtype),
                       None)

    def keep(self, buffers):
        """Keep the buffers that are not None."""
        self.kept.update((k, v) for k, v in buffers._asdict().items() if v is not None)

    def release(self):
        """Let go of the kept volumes (torch's caching allocator keeps their memory)."""
        self.kept.clear()

    def synchronize(self):
        """Wait for the GPU."""
        gpu.synchronize()

    def upload(self, left, right, standardized):
        """Return (pair, standardized pair or None), float32 tensors (2, H, W) on the GPU."""
        stats = [mean_std(g) for g in (left, right)]
        with gpu.current(self.device):
            pair = torch.from_numpy(np.stack([left, right])).to(self.torch_device)
            if not standardized:  # images.standardize on the device
                return pair, None
            return pair, torch.stack([(g - m) / s for g, (m, s) in zip(pair, stats)])

    def to_device(self, cnn):
        """Return host CNN outputs as tensors on the GPU."""
        return CnnConfidence(*(torch.from_numpy(np.ascontiguousarray(a, t)).to(self.torch_device)
                               for a, t in zip(cnn, CNN_TYPES)))

    def cnn_confidence(self, net, pair, max_disp, bf16, radius, scratch, seconds, cancel=None):
        """Return `cnn_cuda.device_confidence` of the standardized pair."""
        with gpu.current(self.device):
            return CnnConfidence(*cnn_cuda.device_confidence(
                net, padded_input(pair[1]), max_disp, bf16, seconds, radius))

    def cost_volume(self, pair, max_disp, cost, window, scale, dtype, out, cancel=None):
        """Return `cost_cuda.cost_volume`: of the gray pair for Census, standardized for SAD."""
        with gpu.current(self.device):
            costs = cost_cuda.cost_volume(pair[0] if cost == 'census' else pair[1], max_disp,
                                          cost, window, out, scale, dtype)
        return CostVolume(costs, max_cost(cost, window) * scale)

    def select_refine(self, volume, cnn, theta, c_hi, c_low, lr_check, plain):
        """Return the refined `volume` and the GCPs (`gcp_cuda.select_refine`)."""
        with gpu.current(self.device):
            gcps = gcp_cuda.select_refine(volume.costs, *cnn, theta, c_hi, c_low, lr_check,
                                          plain)
        return CostVolume(volume.costs, max(volume.top, c_hi)), gcps

    def aggregate(self, volume, p1, p2, paths, out, cancel=None):
        """Return `sgm_cuda.aggregate` of the volume into `out`."""
        with gpu.current(self.device):
            return sgm_cuda.aggregate(volume.costs, p1, p2, paths, volume.top, out)

    def disparity(self, total, cancel=None):
        """Return `sgm_cuda.winners`' integer disparity."""
        with gpu.current(self.device):
            return sgm_cuda.winners(total)[0]

    def winners(self, total, subpixel, cancel=None):
        """Return `sgm_cuda.winners` with the left-right agreement, and the margin."""
        with gpu.current(self.device):
            disp, consistent, s_best, s_second = sgm_cuda.winners(total, subpixel, True)
            return Winners(disp, consistent, disparity_confidence_cuda.margin(s_best, s_second))

    def median(self, disparity):
        """Return the 3x3 median of a (H, W) tensor, edges replicated as cv2.medianBlur."""
        padded = F.pad(disparity[None, None], (1, 1, 1, 1), mode='replicate')[0, 0]
        return padded.unfold(0, 3, 1).unfold(1, 3, 1).reshape(*disparity.shape, 9).median(2)[0]

    def disparity_confidence(self, fit, winners, cnn, gcps):
        """Return `disparity_confidence_cuda.calibrated` of its features."""
        cof_c, cof_d = (None, None) if cnn is None else cnn[:2]
        with gpu.current(self.device):
            planes = disparity_confidence_cuda.features(*winners, cof_c, cof_d, gcps)
            return disparity_confidence_cuda.calibrated(fit, planes)

    def to_host(self, array):
        """Return a tensor as a numpy array (one download)."""
        return array.cpu().numpy()

    def costs_at(self, total, rows, cols, disparities):
        """Return total[rows[i], cols[i], disparities[i, j]], gathered on the GPU."""
        fixed = total.dtype == torch.uint16  # gathered as int16, the same bits
        index = [torch.from_numpy(np.ascontiguousarray(a, np.int64)).to(total.device)
                 for a in (rows[:, None], cols[:, None], disparities)]
        picked = (total.view(torch.int16) if fixed else total)[tuple(index)].cpu().numpy()
        return picked.view(np.uint16) if fixed else picked
