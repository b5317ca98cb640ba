"""A drifting rig in tests: the right view moved down and rolled, as a camera drifts."""
import cv2
import numpy as np


def warp(right: np.ndarray, down: float, roll_deg: float) -> np.ndarray:
    """Return `right` moved down by `down` px and rolled by `roll_deg` about its centre."""
    h, w = right.shape[:2]
    m = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), roll_deg, 1.0)
    m[1, 2] += down
    return cv2.warpAffine(right, m, (w, h), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)
