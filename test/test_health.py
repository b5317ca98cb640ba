"""The view check and the published share: a real pair, and the views a failing camera gives."""
import time

from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.stereo.health import published, ViewCheck
import numpy as np
import pytest


@pytest.fixture(scope='module')
def kitti(data_dir):
    """KITTI 2012 000070, the gray pair as the node takes it (uint8 mono8, 1241x376)."""
    frame = load_frame(data_dir, 'kitti2012/000070_10')
    return frame.left, frame.right


def kinds(findings):
    return [(f.kind, f.text, f.fault) for f in findings]


def test_a_real_pair_is_fine_and_the_same_frame_twice_is_frozen(kitti):
    left, right = kitti
    check = ViewCheck()
    assert check(left, right) == ()
    assert kinds(check(left, right)) == [('frozen', 'left view frozen', True),
                                         ('frozen', 'right view frozen', True)]
    assert check(left[:, ::-1], right[:, ::-1]) == ()  # a new frame: nothing frozen
    assert ViewCheck()(np.dstack([left] * 3), np.dstack([right] * 3)) == ()  # colour


@pytest.mark.parametrize('make, want', [
    (np.zeros_like, [('black', 'right view black', True)]),
    (lambda r: np.full_like(r, 255), [('saturated', 'right view saturated', True)]),
    (lambda r: (r * 0.25).astype(np.uint8),
     [('exposure', 'exposures far apart (right darker)', False)]),
    (lambda r: np.full_like(r, 128), [('texture', 'no texture in the right view', False)]),
])
def test_a_failing_right_view_is_named(kitti, make, want):
    left, right = kitti
    assert kinds(ViewCheck()(left, make(right))) == want


def test_a_twelve_bit_camera_is_scaled_to_its_own_range(kitti):
    """uint16 holding 12 bits (values up to 4080): fine, as at 8 bits; its black view black."""
    left, right = (np.asarray(v, np.uint16) * 16 for v in kitti)
    check = ViewCheck()
    assert check(left, right) == ()
    assert kinds(check(left + 1, right // 40)) == [('black', 'right view black', True)]


def test_published_share_and_confidence():
    disparity = np.full((40, 48), 7.0, np.float32)
    disparity[:, :24] = np.nan  # the left half unpublished
    confidence = np.where(np.isnan(disparity), 0.0, 0.8).astype(np.float32)
    confidence[:20] = np.where(np.isnan(disparity[:20]), 0.0, 0.4)
    share, mean = published(disparity, confidence, (4, 4, 44, 36))
    assert share == pytest.approx(0.5) and mean == pytest.approx(0.6)
    assert published(disparity, None, (4, 4, 44, 36)) == (pytest.approx(0.5), None)
    assert published(disparity, confidence, (0, 4, 24, 36)) == (0.0, None)
    assert published(disparity, confidence, (4, 4, 4, 36)) == (None, None)


def test_the_check_costs_far_less_than_a_frame(kitti):
    """A KITTI frame takes about 0.8 s on 2 cores; the check, well under 5 % of it."""
    left, right = kitti
    check = ViewCheck()
    disparity = np.where(left > 80, 20.0, np.nan).astype(np.float32)
    seconds = []
    for i in range(20):
        start = time.perf_counter()
        check(left, right)
        published(disparity, disparity / 64, (4, 4, 1237, 372))
        seconds.append(time.perf_counter() - start)
    assert np.median(seconds) < 0.005
