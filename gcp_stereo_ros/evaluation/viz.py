"""
Images for people: colour-coded disparities and masks, written as PNG.

A disparity picture (`disparity_picture`) is the TURBO map of the disparity with a colour
bar under it: the scale in px with its ticks, far (small disparities, blue) at the left and
near (large, red) at the right, so that a picture alone says which colour is near.
"""
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike

FONT = cv2.FONT_HERSHEY_SIMPLEX
INK, PAPER = (0, 0, 0), (255, 255, 255)  # the bar's text and background, BGR


def colorize(disp: ArrayLike, max_disp: float) -> np.ndarray:
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


def disparity_picture(disp: ArrayLike, max_disp: float, width: int | None = None) -> np.ndarray:
    """
    Return `colorize(disp, max_disp)` with its colour bar under it, uint8 BGR.

    `width`: the map is first resized to this many pixels across (area interpolation,
    the aspect kept), and the bar drawn at that width. The bar (`colour_bar`) spans
    0 .. max_disp px, far at the left, near at the right.
    """
    image = colorize(disp, max_disp)
    if width is not None:
        if not (isinstance(width, int) and width >= 1):
            raise ValueError(f'width must be a whole number of pixels >= 1, got {width!r}')
        h, w = image.shape[:2]
        image = cv2.resize(image, (width, max(1, round(h * width / w))),
                           interpolation=cv2.INTER_AREA)
    return np.vstack([image, colour_bar(image.shape[1], max_disp)])


def colour_bar(width: int, max_disp: float, label: str = 'disparity (px)') -> np.ndarray:
    """
    Return the colour bar of `colorize` over [0, max_disp]: uint8 BGR (h, width, 3).

    White, with a strip of the colour map (the colour at column x is that of the disparity
    `bar_value(x)`), ticks at round values under it and their numbers, then 'far' at the
    left end, `label` in the middle and 'near' at the right end.
    """
    scale = float(np.clip(width / 800, 0.4, 1.0))
    thick = 1 if scale < 0.7 else 2
    pad = round(6 * scale) + 2
    text_h = cv2.getTextSize('0', FONT, scale, thick)[0][1]
    x0, x1 = bar_ends(width, max_disp)
    strip = round(14 * scale) + 4
    tick = round(5 * scale) + 2
    words = sum(cv2.getTextSize(t, FONT, scale, thick)[0][0] for t in ('far', label, 'near'))
    lines = 2 if words + 8 * pad <= width else 3  # a narrow bar: the label on its own line
    bar = np.full((pad + strip + tick + lines * (pad + text_h) + pad + thick, width, 3), PAPER,
                  np.uint8)
    values = bar_value(np.arange(x0, x1 + 1), width, max_disp)
    bar[pad:pad + strip, x0:x1 + 1] = colorize(values[None], max_disp)
    y = pad + strip
    step = tick_step(max_disp, x1 - x0, scale, thick)
    for v in np.arange(0, max_disp // step * step + step / 2, step):  # 0 .. <= max_disp
        x = round(x0 + v / max_disp * (x1 - x0))
        cv2.line(bar, (x, y), (x, y + tick), INK, thick)
        _text(bar, f'{v:g}', x, y + tick + pad + text_h, scale, thick, 'centre')
    y += tick + 2 * (pad + text_h)
    _text(bar, 'far', x0, y, scale, thick, 'left')
    _text(bar, 'near', x1, y, scale, thick, 'right')
    _text(bar, label, width // 2, y + (lines - 2) * (pad + text_h), scale, thick, 'centre')
    return bar


def bar_ends(width: int, max_disp: float) -> tuple[int, int]:
    """Return the first and last column of the colour strip of a bar `width` px across."""
    scale = float(np.clip(width / 800, 0.4, 1.0))
    widest = max(cv2.getTextSize(t, FONT, scale, 2)[0][0] for t in (f'{max_disp:g}', 'near'))
    margin = min(widest // 2 + 4, max(0, (width - 2) // 4))
    return margin, width - 1 - margin


def bar_value(x: ArrayLike, width: int, max_disp: float) -> np.ndarray:
    """Return the disparity whose colour the bar `width` px across shows at column(s) `x`."""
    x0, x1 = bar_ends(width, max_disp)
    return np.float32(max_disp) * (np.asarray(x, np.float32) - x0) / max(x1 - x0, 1)


def tick_step(max_disp: float, length: float, scale: float, thick: int) -> float:
    """Return the round tick step (1, 2, 5 x 10^k) whose numbers fit apart on `length` px."""
    wide = cv2.getTextSize(f'{max_disp:g}', FONT, scale, thick)[0][0] * 1.5
    step = 10.0 ** np.floor(np.log10(max_disp / 10)) if max_disp >= 10 else 1.0
    while True:
        for factor in (1, 2, 5):
            if step * factor >= max_disp or step * factor / max_disp * length >= wide:
                return step * factor
        step *= 10


def _text(image: np.ndarray, text: str, x: float, baseline: float, scale: float, thick: int,
          align: str) -> None:
    """Write `text` with its baseline at `baseline`, left/centre/right-aligned at column x."""
    w = cv2.getTextSize(text, FONT, scale, thick)[0][0]
    left = {'left': x, 'centre': x - w // 2, 'right': x - w}[align]
    cv2.putText(image, text, (int(left), int(baseline)), FONT, scale, INK, thick, cv2.LINE_AA)


def save_png(path: str | Path, image: np.ndarray) -> None:
    """Write `image` (gray or BGR, OpenCV order) to `path`, creating parent folders."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image):
        raise OSError(f'could not write {path}')
