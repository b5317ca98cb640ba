"""CUDA twin of gcp.py's `select` and `refine`, in one pass over a volume in GPU memory."""
from numba import cuda
import numpy as np
import torch

from . import gpu
from ..gcp import levels


@cuda.jit
def _select_refine(cost: gpu.DeviceArray, cof_c: gpu.DeviceArray, cof_d: gpu.DeviceArray,
                   cof_dr: gpu.DeviceArray, plain: gpu.DeviceArray, theta: float, lr_check: bool,
                   plain_check: bool, c_hi: float, c_low: float, gcp: gpu.DeviceArray) -> None:
    """One thread per pixel: the GCP rule of `gcp.select`, then the refinement of `refine`."""
    h, w, nd = cost.shape
    i = cuda.grid(1)
    if i >= h * w:
        return
    y, x = i // w, i % w
    d = cof_d[y, x]
    keep = cof_c[y, x] > theta
    if keep and lr_check:  # gcp.right_view_agrees with a tolerance of 1 px
        keep = x - d >= 0 and abs(cof_dr[y, x - d] - d) <= 1
    if keep and plain_check:  # at most 1 px above plain SGM's disparity
        keep = d - plain[y, x] <= 1
    gcp[y, x] = keep
    if keep:
        if 0 <= d < nd:
            cost[y, x, d] = c_low
    else:
        for k in range(nd):
            cost[y, x, k] = c_hi


def select_refine(cost: torch.Tensor, cof_c: torch.Tensor, cof_d: torch.Tensor,
                  cof_dr: torch.Tensor, theta: float, c_hi: float, c_low: float,
                  lr_check: bool = False, plain: torch.Tensor | None = None) -> torch.Tensor:
    """
    Refine `cost` in place with the GCPs `gcp.select` picks; return the GCP mask.

    Tensors on the device: `cost` (H, W, D) float32 or uint16, the float32 confidence
    `cof_c`, the int32 CNN disparities `cof_d`, `cof_dr` and plain SGM's float32 disparity
    `plain` (H, W; None: not checked). The mask is bool (H, W).
    """
    c_hi, c_low = levels(gpu.numpy_type(cost), c_hi, c_low)
    gcp = torch.empty(cost.shape[:2], dtype=torch.bool, device=cost.device)
    checked = plain is not None  # else a stand-in the kernel never reads
    plain = plain if checked else torch.zeros((1, 1), dtype=torch.float32, device=cost.device)
    gpu.launch(_select_refine, gcp.numel(), cost, cof_c, cof_d, cof_dr, plain,
               np.float32(theta), bool(lr_check), checked, c_hi, c_low, gcp)
    return gcp
