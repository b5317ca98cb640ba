"""
The misalignment estimate and its correction on real pairs with known warps.

The right view is warped as a drifting rig would: moved down and rolled about the image's
centre (cv2.warpAffine, bilinear); the estimate must move by what was applied and the
correction must undo it. Textureless, dark and differently exposed pairs must say they do
not know, or change nothing.
"""
import cv2
from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.evaluation.metrics import error_rates
from gcp_stereo_ros.stereo.alignment import correct, estimate, fold, Misalignment, TERMS
from gcp_stereo_ros.stereo.config import StereoConfig
from gcp_stereo_ros.stereo.images import gray_pair
from gcp_stereo_ros.stereo.pipeline import StereoPipeline
import numpy as np
import pytest
from rig import warp


def edges(shape, down, roll_deg):
    """Return the vertical offsets (left edge, right edge) at the middle row that a warp makes."""
    half = (shape[1] - 1) / 2
    at_edge = half * np.sin(np.radians(roll_deg))
    return down + at_edge, down - at_edge


@pytest.fixture(scope='module')
def kitti(data_dir):
    """KITTI 2015 000001 (a training frame of the CNN), gray float32."""
    frame = load_frame(data_dir, 'kitti2015/000001_10')
    return (*gray_pair(frame.left, frame.right), frame)


@pytest.mark.parametrize('down, roll', [(0.5, 0.0), (2.0, 0.0), (0.0, 0.2), (1.0, 0.3)])
def test_the_estimate_moves_by_the_applied_warp(kitti, down, roll):
    left, right, _ = kitti
    before = estimate(left, right, 128)
    after = estimate(left, warp(right, down, roll), 128)
    assert before.known and after.known
    want = edges(left.shape, down, roll)
    assert abs(after.left_edge - before.left_edge - want[0]) < 0.05
    assert abs(after.right_edge - before.right_edge - want[1]) < 0.05
    assert after.matches > 200 and after.residual < 0.3 and after.error < 0.05


def test_the_kitti_pair_itself_is_a_fifth_of_a_pixel_off(kitti):
    m = estimate(kitti[0], kitti[1], 128)
    assert 0.15 < m.term('offset') < 0.4 and m.largest > 0.3
    assert m.verdict() == 'corrected'
    errors = dict(zip(TERMS, m.errors))
    assert 0.003 < errors['offset'] < 0.03 and errors['keystone'] == 0  # not fitted
    assert m.term('offset') > 3 * errors['offset']


def test_a_term_the_data_does_not_support_is_not_used():
    """The coefficients keep a term only at 3 standard errors; below MIN_CORRECTION: nothing."""
    m = Misalignment(True, (0.2, 0.3, 0.5, 0, 0, 0), (0.05, 0.2, 0.1, 0, 0, 0), (375, 1242))
    assert m.coefficients == (0.2, 0.0, 0.5, 0, 0, 0)
    weak = Misalignment(True, (0.2, 0.3, 0, 0, 0, 0), (0.01, 0.2, 0, 0, 0, 0), (375, 1242))
    assert weak.largest == pytest.approx(0.2) and 'below' in weak.verdict()
    right = np.zeros((375, 1242), np.float32)
    assert correct(right, weak) is right


def test_after_the_correction_the_pair_lines_up(kitti):
    left, right, _ = kitti
    warped = warp(right, 1.5, -0.2)
    m = estimate(left, warped, 128)
    fixed = correct(warped, m)
    assert fixed.dtype == np.float32 and fixed.shape == left.shape
    again = estimate(left, fixed, 128)
    assert again.known and again.largest < 0.1


def test_the_pipeline_undoes_a_drift_by_default(data_dir):
    """Middlebury cones (a validation frame) moved down 2 px: 3.54 -> 26.2 -> 3.20 % wrong."""
    frame = load_frame(data_dir, 'middlebury_v2/cones')
    pipe = StereoPipeline(StereoConfig(max_disp=frame.max_disp))
    as_is = pipe.with_config(pipe.config.replace(align=False))
    left, right = gray_pair(frame.left, frame.right)
    aligned = error_rates(as_is(left, right).disparity, frame.gt, frame.valid)
    warped = warp(right, 2.0, 0.0)
    drifted = error_rates(as_is(left, warped).disparity, frame.gt, frame.valid)
    result = pipe(left, warped)
    corrected = error_rates(result.disparity, frame.gt, frame.valid)
    assert drifted['bad3'] > aligned['bad3'] + 15
    assert abs(corrected['bad3'] - aligned['bad3']) < 0.5
    assert abs(corrected['density'] - aligned['density']) < 2
    m = result.misalignment
    assert m.verdict() == 'corrected' and abs(m.term('offset') - 2 + 0.08) < 0.05
    assert 'align' in result.seconds and as_is(left, right).misalignment is None
    assert StereoConfig.for_cost('census', 'paper').align is False


@pytest.mark.parametrize('case', ['aligned', 'flat', 'dark'])
def test_a_pair_it_leaves_alone_gives_the_same_bits(data_dir, case):
    """A well rectified pair (cones, 0.08 px), a textureless and a dark one: as without align."""
    frame = load_frame(data_dir, 'middlebury_v2/cones')
    left, right = gray_pair(frame.left, frame.right)
    if case == 'flat':
        left = right = np.full_like(left, 90)
    elif case == 'dark':
        rng = np.random.default_rng(1)
        left, right = (rng.poisson(1.0, left.shape).astype(np.float32) for _ in range(2))
    config = StereoConfig(max_disp=frame.max_disp, use_gcp=False)
    result = StereoPipeline(config)(left, right)
    off = StereoPipeline(config.replace(align=False))(left, right)
    np.testing.assert_array_equal(result.disparity, off.disparity)
    m = result.misalignment
    assert m.known == (case == 'aligned') and m.verdict() != 'corrected'
    assert m.cause == {'aligned': '', 'flat': 'textureless', 'dark': 'dark'}[case]


def test_other_lighting_in_the_right_view(kitti):
    """Gamma, a gain that falls across the image and an offset: the same estimate."""
    left, right, _ = kitti
    ramp = np.linspace(1.3, 0.5, right.shape[1], dtype=np.float32)[None]
    lit = np.clip(255 * (right / 255) ** 0.6 * ramp + 20, 0, 255)
    a, b = estimate(left, right, 128), estimate(left, lit, 128)
    assert b.known and b.matches > 0.8 * a.matches
    assert abs(a.left_edge - b.left_edge) < 0.1 and abs(a.right_edge - b.right_edge) < 0.1


@pytest.mark.parametrize('gain, known', [(0.25, True), (2.5, True), (4.0, False)])
def test_a_differently_exposed_pair_changes_nothing(data_dir, gain, known):
    """Cones (within 0.08 px) with the right view 2 stops darker or blown out: left alone."""
    frame = load_frame(data_dir, 'middlebury_v2/cones')
    left, right = frame.left, frame.right
    exposed = np.clip(np.round(right.astype(np.float32) * gain), 0, 255).astype(np.uint8)
    m = estimate(left, exposed, frame.max_disp)
    assert m.known == known
    assert m.largest < 0.15 if known else m.cause == 'saturated'
    assert correct(exposed, m) is exposed


def test_repetitive_texture_and_a_moving_object(kitti):
    """Stripes pasted out of phase into a fifth of both views, a car moved 4 px: no change."""
    left, right, _ = kitti
    h, w = left.shape
    stripes = 128 + 100 * np.sign(np.sin(np.arange(w) * 2 * np.pi / 9))[None].astype(np.float32)
    left2, right2 = left.copy(), right.copy()
    left2[:, 100:350] = stripes[:, 100:350]
    right2[:, 100:350] = stripes[:, 104:354]
    right2[200:300, 700:900] = right[196:296, 700:900]
    a, b = estimate(left, right, 128), estimate(left2, right2, 128)
    assert b.known
    assert abs(a.left_edge - b.left_edge) < 0.1 and abs(a.right_edge - b.right_edge) < 0.1


@pytest.mark.parametrize('case, cause', [('flat', 'textureless'), ('ramp', 'textureless'),
                                         ('dark', 'dark'), ('black', 'dark')])
def test_no_texture_or_a_dark_frame_is_unknown_and_nothing_changes(kitti, case, cause):
    left, right, _ = kitti
    rng = np.random.default_rng(0)
    h, w = left.shape
    if case == 'flat':
        left = right = np.full((h, w), 90, np.uint8)
    elif case == 'ramp':
        left = right = np.tile(np.linspace(0, 255, w, dtype=np.float32), (h, 1))
    elif case == 'dark':  # sensor noise of a night frame: no scene at all
        left, right = (rng.poisson(1.0, (h, w)).astype(np.uint8) for _ in range(2))
    else:
        left = right = np.zeros((h, w), np.uint8)
    m = estimate(left, right, 128)
    assert not m.known and m.reason and m.largest == 0 and m.cause == cause
    assert m.coefficients == (0.0,) * len(TERMS) and m.verdict().startswith('unknown')
    assert correct(right, m) is right


def test_a_darkened_pair_is_measured_or_unknown(kitti):
    """The KITTI pair at a fortieth of its brightness, 8 bits: right, or it says it can't tell."""
    left, right, _ = kitti
    truth = estimate(left, right, 128)
    dark = [np.round(g / 40).astype(np.uint8) for g in (left, right)]
    m = estimate(*dark, 128)
    if m.known:
        assert abs(m.left_edge - truth.left_edge) < 0.1
        assert abs(m.right_edge - truth.right_edge) < 0.1


def test_small_or_too_large_misalignment_leaves_the_image_alone(kitti):
    right = kitti[1]
    m = Misalignment(True, (0.05, 0.03, 0, 0, 0, 0), shape=right.shape)
    assert m.largest == pytest.approx(0.08) and correct(right, m) is right
    moved = correct(right, Misalignment(True, (1.0, 0, 0, 0, 0, 0), shape=right.shape))
    np.testing.assert_allclose(moved[10:-10], right[11:-9], atol=1e-3)
    far = Misalignment(True, (9.0, 0, 0, 0, 0, 0), shape=right.shape)
    assert 'too large' in far.verdict() and correct(right, far) is right


def test_the_correction_folds_into_rectification_maps(kitti):
    """One remap through the folded maps gives the corrected image (bilinear, not Lanczos)."""
    right = kitti[1]
    m = estimate(kitti[0], warp(right, 1.5, -0.2), 128)
    h, w = right.shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    mx, my = fold(m, x + 0.5, y)  # a rectification that moves the image half a pixel left
    once = cv2.remap(right, mx, my, cv2.INTER_LINEAR)
    twice = correct(cv2.remap(right, x + 0.5, y, cv2.INTER_LINEAR), m)
    inner = (slice(20, -20), slice(20, -20))
    assert np.abs(once[inner] - twice[inner]).mean() < 1.0  # grey levels, of 0-255


def test_the_field_and_its_edges():
    m = Misalignment(True, (0.5, 1.0, -0.2, 0.1, 0.05, 0.0), shape=(101, 201))
    assert m.left_edge == pytest.approx(0.5 - 1.0 + 0.05)
    assert m.right_edge == pytest.approx(0.5 + 1.0 + 0.05)
    assert m.at(200, 100) == pytest.approx(0.5 + 1.0 - 0.2 + 0.1 + 0.05)
    y, x = np.mgrid[0:101, 0:201]
    assert m.largest == pytest.approx(np.abs(m.at(x, y)).max())


def test_bad_input_says_what_is_wrong(kitti):
    left, right, _ = kitti
    with pytest.raises(ValueError, match='same size|one size'):
        estimate(left, right[:, :-1])
    m = estimate(left, warp(right, 1.0, 0.0), 128)
    with pytest.raises(ValueError, match='estimated on 1242x375'):
        correct(right[:, :-1], m)
    tiny = estimate(left[:20, :20], right[:20, :20])
    assert not tiny.known and 'too small' in tiny.reason and tiny.cause == 'small'
