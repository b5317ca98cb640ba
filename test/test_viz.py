"""Disparity pictures carry a colour bar that says their scale in px and which colour is near."""
import cv2
from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.evaluation.viz import (bar_ends, bar_value, colorize, colour_bar,
                                           disparity_picture)
from gcp_stereo_ros.tools import evaluate
import numpy as np
import pytest

TURBO = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0]


def colour_key(image):
    """Return each BGR pixel of `image` as one integer."""
    b, g, r = (image[..., i].astype(np.int64) for i in range(3))
    return b << 16 | g << 8 | r


def turbo_level(image):
    """Return the TURBO level (0..255) of each BGR pixel of `image`, -1 if not a map colour."""
    keys = colour_key(TURBO)
    assert len(set(keys)) == 256  # each level its own colour
    order = np.argsort(keys)
    at = np.clip(np.searchsorted(keys[order], colour_key(image)), 0, 255)
    return np.where(keys[order][at] == colour_key(image), order[at], -1)


@pytest.mark.parametrize('width, max_disp', [(741, 128), (1241, 128), (480, 256), (300, 64),
                                             (120, 7)])
def test_the_bar_runs_through_the_colour_map_from_far_to_near(width, max_disp):
    bar = colour_bar(width, max_disp)
    x0, x1 = bar_ends(width, max_disp)
    assert 0 <= x0 < x1 < width and x1 - x0 >= width // 2
    levels = turbo_level(bar[:, x0:x1 + 1])
    rows = [y for y in range(bar.shape[0]) if levels[y].min() >= 0]  # all map colours
    assert len(rows) >= 8 and rows == list(range(rows[0], rows[-1] + 1)), rows  # one strip
    for level in levels[rows]:
        assert (np.diff(level) >= 0).all()  # monotonic: small disparity left, large right
        assert level[0] <= 1 and level[-1] >= 254
        want = np.clip(bar_value(np.arange(x0, x1 + 1), width, max_disp) * 255 / max_disp, 0, 255)
        assert np.abs(level - want).max() <= 2  # bar_value says the disparity of each column
    ink = bar.min(-1) < 100  # the ticks' numbers and the words under the strip
    assert not ink[:rows[0]].any()
    ticks = np.flatnonzero(ink[rows[-1] + 1])
    assert len(ticks) >= 2 and x0 - 1 <= ticks[0] <= x0 + 1 and ticks[-1] <= x1 + 1, ticks
    below = ink[rows[-1] + 1:]
    assert below[:, :width // 4].sum() > 20 and below[:, -(width // 4):].sum() > 20  # far, near
    assert below[:, width // 3:2 * width // 3].sum() > 20  # the label in the middle


def test_picture_is_the_map_over_its_bar():
    disp = np.tile(np.linspace(0, 100, 400, dtype=np.float32), (120, 1))
    disp[:10] = np.nan
    picture = disparity_picture(disp, 128)
    bar = colour_bar(400, 128)
    assert picture.shape == (120 + bar.shape[0], 400, 3) and bar.shape[0] > 40
    np.testing.assert_array_equal(picture[:120], colorize(disp, 128))
    np.testing.assert_array_equal(picture[120:], bar)
    small = disparity_picture(disp, 128, width=200)
    assert small.shape[:2] == (60 + colour_bar(200, 128).shape[0], 200)
    for width in (0, 2.5):
        with pytest.raises(ValueError, match='width must be'):
            disparity_picture(disp, 128, width=width)


def test_eval_out_writes_pictures_with_the_bar(data_dir, tmp_path):
    frame = load_frame(str(data_dir), 'middlebury_v2/tsukuba')
    assert evaluate.main(['--dataset', str(data_dir), '--frames', 'middlebury_v2/tsukuba',
                          '--methods', 'census', '--paths', '4', '--out', str(tmp_path)]) == 0
    picture = cv2.imread(str(tmp_path / 'middlebury_v2_tsukuba_census.png'))
    h, w = frame.left.shape[:2]
    bar = colour_bar(w, frame.max_disp)
    assert picture.shape == (h + bar.shape[0], w, 3)
    np.testing.assert_array_equal(picture[h:], bar)
    disp, _, _ = evaluate.Runner(paths=4).run('census', frame.left, frame.right, frame.max_disp)
    np.testing.assert_array_equal(picture[:h], colorize(disp, frame.max_disp))
