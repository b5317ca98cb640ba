"""
What a stereo pair says about itself: its views' health and how much of it was published.

ROS-free and cheap: every look is at a thumbnail of every STEP-th pixel of each view (a
1242x375 pair: 311x94 samples). `ViewCheck` names what is wrong
with the views of a pair, each finding (`Finding`) at these levels, as fractions of the
full scale (255 for uint8; for uint16 the smallest of 2^8 - 1, 2^10 - 1, ... 2^16 - 1 at or
above the brightest sample seen so far, so a 12-bit camera's scale is 4095):

- black: a view's mean below BLACK (0.05);
- saturated: more than SATURATED_SHARE (half) of a view at or above SATURATED (0.98);
- frozen: a view identical to its own previous one, as no camera's noise leaves it;
- exposures far apart: one view's mean more than EXPOSURE_RATIO (2) times the other's;
- no texture: a view's mean absolute difference between horizontal neighbours (STEP px
  apart) below TEXTURE (0.004).

Real frames lie well inside these levels (doc/node.md, "Whether to trust the depth").

A black, saturated or frozen view is a fault (`Finding.fault`): its depth cannot be right;
the others are conditions that explain a collapse of what is published. `published`
measures that: the share of the valid window published and its disparity confidence.
"""
from typing import NamedTuple

import numpy as np

from .images import to_gray

STEP = 4  # px between two samples of a thumbnail, in rows and columns
BLACK = 0.05  # a view's mean below this fraction of the full scale: black
SATURATED = 0.98  # a sample at or above this fraction of the full scale is saturated
SATURATED_SHARE = 0.5  # more samples saturated than this share: the view is saturated
EXPOSURE_RATIO = 2.0  # one view's mean more than this many times the other's: far apart
TEXTURE = 0.004  # mean |horizontal difference| below this fraction of the scale: no texture
FAULTS = ('black', 'saturated', 'frozen')  # the kinds of finding that are faults
_SCALES = (255, 1023, 4095, 16383, 65535)  # full scales of 8 to 16 bits a sample


class Finding(NamedTuple):
    """
    One thing wrong with a pair's views.

    `kind` is one of 'black', 'saturated', 'frozen', 'exposure', 'texture'; `text` names it
    with its side and stays the same from frame to frame ('right view black').
    """

    kind: str
    text: str

    @property
    def fault(self) -> bool:
        """Return True for a black, saturated or frozen view: its depth cannot be right."""
        return self.kind in FAULTS


def thumbnail(image: np.ndarray) -> np.ndarray:
    """
    Return every STEP-th pixel of `image` as float32 gray (H / STEP, W / STEP), unscaled.

    `image`: what `images.to_gray` takes (colour as RGB: BGR gives other weights, alike).
    """
    return to_gray(np.asarray(image)[::STEP, ::STEP])


class ViewCheck:
    """
    Name what is wrong with the views of each pair, remembering each side's last view.

    Call it with each pair as the node has it (uint8 or uint16, gray or colour, the same
    size); it returns the findings, faults first, () when the views look fine.
    """

    def __init__(self) -> None:
        self._previous: dict[str, np.ndarray] = {}
        self._scale = 0.0

    def __call__(self, left: np.ndarray, right: np.ndarray) -> tuple[Finding, ...]:
        """Return the findings of this pair (see the module's docstring for the levels)."""
        views = {'left': thumbnail(left), 'right': thumbnail(right)}
        peak = max(float(v.max(initial=0.0)) for v in views.values())
        wide = np.asarray(left).dtype != np.uint8
        self._scale = max(self._scale, next((s for s in _SCALES if s >= peak), _SCALES[-1])
                          if wide else 255.0)
        faults, conditions = [], []
        means = {}
        for side, view in views.items():
            scaled = view / self._scale
            means[side] = float(scaled.mean())
            previous = self._previous.get(side)
            if means[side] < BLACK:
                faults.append(Finding('black', f'{side} view black'))
            elif (scaled >= SATURATED).mean() > SATURATED_SHARE:
                faults.append(Finding('saturated', f'{side} view saturated'))
            elif float(np.abs(np.diff(scaled, axis=1)).mean()) < TEXTURE:
                conditions.append(Finding('texture', f'no texture in the {side} view'))
            if previous is not None and np.array_equal(previous, view):
                faults.append(Finding('frozen', f'{side} view frozen'))
            self._previous[side] = view
        lit = all(f.kind == 'frozen' for f in faults)  # neither view black nor saturated
        if lit and max(means.values()) > EXPOSURE_RATIO * min(means.values()):
            darker = min(means, key=lambda side: means[side])
            conditions.insert(0, Finding('exposure', f'exposures far apart ({darker} darker)'))
        return tuple(faults + conditions)


def published(disparity: np.ndarray, confidence: np.ndarray | None,
              window: tuple[int, int, int, int]) -> tuple[float | None, float | None]:
    """
    Return the share of `window` published and the mean confidence of what was, sampled.

    `window` (x0, y0, x1, y1), px: the DisparityImage's valid_window
    (postprocess.valid_window), where the matching window lies inside the image.
    `disparity`: float32 (H, W), NaN where nothing is published; `confidence`: the
    disparity confidence in [0, 1], or None (no fit: then None). Both in [0, 1] (typical
    on KITTI 2012 000070 with the defaults: 0.75 and 0.98); None for an empty window.
    """
    x0, y0, x1, y1 = window
    disp = disparity[y0:y1:STEP, x0:x1:STEP]
    if disp.size == 0:
        return None, None
    valid = ~np.isnan(disp)
    share = float(valid.mean())
    if confidence is None or not valid.any():
        return share, None
    return share, float(confidence[y0:y1:STEP, x0:x1:STEP][valid].mean())
