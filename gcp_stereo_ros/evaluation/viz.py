"""Images for people: colour-coded disparities and masks, written as PNG."""
from pathlib import Path

import cv2
import numpy as np


def colorize(disp, max_disp):
    """
    Return a uint8 BGR (H, W, 3) TURBO rendering of `disp` over [0, max_disp].

    NaN, inf and negative values are black.
    """
    if not max_disp > 0:
        raise ValueError(f'max_disp must be positive, got {max_disp}')
    d = np.asarray(disp, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f'expected a (H, W) disparity map, got shape {d.shape}')
    known = np.isfinite(d) & (d >= 0)
    scaled = np.clip(np.where(known, d, 0) * (255.0 / max_disp), 0, 255).astype(np.uint8)
    image = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)
    image[~known] = 0
    return image


def save_png(path, image):
    """Write `image` (gray or BGR, OpenCV order) to `path`, creating parent folders."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image):
        raise OSError(f'could not write {path}')
