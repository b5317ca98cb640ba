"""
The disparity confidence on a GPU: torch twins of `disparity_confidence`'s functions.

`margin`, `features` and `calibrated` (a `ConfidenceFit` applied) equal the host's within
float rounding: cv2's box filter and torch's pooling sum in other orders.
"""
import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F

from ..disparity_confidence import AROUND, CONFIDENCE_FEATURES, ConfidenceFit, WIDE


def margin(s_best: torch.Tensor, s_second: torch.Tensor) -> torch.Tensor:
    """Return `disparity_confidence.margin` of device tensors."""
    m = 1.0 - s_best.double() / s_second.double()
    return torch.where(torch.isfinite(m), m.clamp(0.0, 1.0), 1.0).float()


def _reflect_101(n: int, pad: int) -> npt.NDArray[np.int64]:
    """Return the indices of 0 .. n - 1 padded by `pad` as cv2's BORDER_REFLECT_101."""
    i = np.arange(-pad, n + pad)
    if n == 1:
        return np.zeros_like(i)
    period = 2 * (n - 1)
    i = np.abs(i) % period
    return np.where(i >= n, period - i, i)


def _box_mean(x: torch.Tensor, size: int) -> torch.Tensor:
    """Return cv2.blur(x, (size, size)) of a (H, W) tensor (borders reflected, 101)."""
    pad = size // 2
    rows, cols = (torch.from_numpy(_reflect_101(n, pad)).to(x.device) for n in x.shape)
    padded = x.index_select(0, rows).index_select(1, cols)
    return F.avg_pool2d(padded[None, None], size, stride=1)[0, 0]


def _max_filter(x: torch.Tensor, size: int) -> torch.Tensor:
    """Return cv2.dilate(x, ones((size, size))) of a (H, W) tensor (borders replicated)."""
    padded = F.pad(x[None, None], (size // 2,) * 4, mode='replicate')
    return F.max_pool2d(padded, size, stride=1)[0, 0]


def features(disp: torch.Tensor, consistent: torch.Tensor, m: torch.Tensor,
             cof_c: torch.Tensor | None, cof_d: torch.Tensor | None, gcp: torch.Tensor | None
             ) -> torch.Tensor:
    """Return `disparity_confidence.features` of device tensors, float32 (n, H, W)."""
    planes = torch.zeros((len(CONFIDENCE_FEATURES), *disp.shape), dtype=torch.float32,
                         device=disp.device)
    (cnn, on_gcp, agrees, margin_, sqrt_margin, lr, lr_around, margin_around, spread, above,
     log_disp, lr_wide, margin_wide) = planes
    if cof_c is not None:
        cnn.copy_(cof_c)
        on_gcp.copy_(gcp)
        # numpy's float64; cof_d is None only with cof_c
        agrees.copy_((cof_d.double() - disp.double()).abs() <= 1)  # type: ignore[union-attr]
    margin_.copy_(m)
    lr.copy_(consistent)
    torch.sqrt(m, out=sqrt_margin)
    low, high = -_max_filter(-disp, AROUND), _max_filter(disp, AROUND)
    for src, dst, size in ((lr, lr_around, AROUND), (m, margin_around, AROUND),
                           (lr, lr_wide, WIDE), (m, margin_wide, WIDE)):
        dst.copy_(_box_mean(src, size))
    for value, dst in ((high - low, spread), (disp - low, above), (disp, log_disp)):
        torch.log1p(value.clamp(min=0), out=dst)
    return planes


def calibrated(fit: ConfidenceFit, planes: torch.Tensor) -> torch.Tensor:
    """Return `fit(planes)` (a `ConfidenceFit`) of device planes, float32."""
    coef = torch.from_numpy(fit.coef.astype(np.float32)).to(planes.device)
    score = (torch.tensordot(coef[1:], planes, 1) + coef[0]).double()
    xp, fp = (torch.from_numpy(k).to(planes.device) for k in fit.knots)
    j = torch.searchsorted(xp, score, right=True).clamp(1, len(xp) - 1) - 1
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    out = slope * (score - xp[j]) + fp[j]  # np.interp's formula
    out = torch.where(score < xp[0], fp[0], torch.where(score >= xp[-1], fp[-1], out))
    return out.float()
