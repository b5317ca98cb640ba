"""Error rates on a hand-made case with known answers."""
from gcp_stereo_ros.evaluation.metrics import (error_rates, interpolate_background,
                                               sparsification, sparsification_area)
import numpy as np
import pytest


def test_hand_made_case():
    gt = np.array([[10.0, 10.0, 10.0, 10.0],
                   [10.0, 10.0, np.nan, 10.0]])
    disp = np.array([[10.5, 11.5, 12.5, 14.0],
                     [16.0, np.nan, 0.0, np.inf]])
    # errors at the 5 published pixels: 0.5, 1.5, 2.5, 4, 6 (+4 and +6 too near); the two
    # unpublished ones are filled from their row: (1, 1) with min(16, 0) = 0 (error 10), (1, 3)
    # with 0 extrapolated (error 10)
    r = error_rates(disp, gt)
    assert r['bad1'] == pytest.approx(100 * 6 / 7)
    assert r['bad2'] == pytest.approx(100 * 5 / 7)
    assert r['bad3'] == pytest.approx(100 * 4 / 7)
    assert r['bad5'] == pytest.approx(100 * 3 / 7)
    assert r['density'] == pytest.approx(100 * 5 / 7)
    assert r['bad3_published'] == pytest.approx(100 * 2 / 5)
    assert r['bad1_published'] == pytest.approx(100 * 4 / 5)
    assert r['near3_published'] == pytest.approx(100 * 2 / 5)
    assert r['mae'] == pytest.approx((0.5 + 1.5 + 2.5 + 4 + 6) / 5)
    assert set(r) == {'bad1', 'bad2', 'bad3', 'bad5', 'mae', 'density', 'bad1_published',
                      'bad2_published', 'bad3_published', 'bad5_published', 'near3_published'}


def test_background_interpolation_as_the_kitti_devkit():
    nan = np.nan
    disp = np.array([[nan, 5.0, nan, nan, 9.0, nan],
                     [nan, nan, nan, nan, nan, nan],
                     [2.0, nan, 7.0, nan, nan, 4.0]])
    # rows: gaps between two valid pixels take the smaller, ends the nearest; then the empty
    # row takes each column's nearest valid value (from above first: the top extrapolation
    # only fills rows above the first valid one, the bottom one below the last)
    want = np.array([[5.0, 5.0, 5.0, 5.0, 9.0, 9.0],
                     [5.0, 5.0, 5.0, 5.0, 9.0, 9.0],
                     [2.0, 2.0, 7.0, 4.0, 4.0, 4.0]])
    got = interpolate_background(disp)
    np.testing.assert_array_equal(got[[0, 2]], want[[0, 2]])
    assert np.isnan(got[1]).all()  # between two valid rows the devkit fills nothing
    np.testing.assert_array_equal(interpolate_background(disp[:2]), want[:2])
    assert np.isnan(interpolate_background(np.full((2, 2), nan))).all()


def test_sparsification():
    wrong = np.array([True, False, False, True, False])
    score = np.array([0.1, 0.9, 0.8, 0.2, 0.7])  # ranks every wrong pixel last
    fractions, rates = sparsification(wrong, score, steps=5)
    np.testing.assert_allclose(rates, [0, 0, 0, 25, 40])
    assert sparsification_area(fractions, rates) == pytest.approx(0.2 * (12.5 + 32.5))
    _, worst = sparsification(wrong, -score, steps=5)
    assert sparsification_area(fractions, worst) > sparsification_area(fractions, rates)


def test_valid_mask_restricts_evaluation():
    gt = np.array([[1.0, 2.0, 3.0]])
    disp = np.array([[1.0, 9.0, np.nan]])
    r = error_rates(disp, gt, valid=np.array([[True, False, True]]))
    assert r['bad1'] == pytest.approx(50.0)  # (0, 2) filled with 9: error 6
    assert r['mae'] == 0.0 and r['density'] == 50.0
    r = error_rates(disp, gt, valid=np.array([[False, False, True]]))
    assert r['bad5'] == 100.0 and np.isnan(r['mae']) and r['density'] == 0.0


def test_perfect_estimate():
    gt = np.linspace(0, 60, 20).reshape(4, 5)
    r = error_rates(gt, gt)
    assert r['density'] == 100.0 and r['mae'] == 0.0
    assert all(v == 0.0 for k, v in r.items() if k.startswith(('bad', 'near')))


def test_bad_input():
    with pytest.raises(ValueError, match='shape'):
        error_rates(np.zeros((2, 3)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match='valid mask has shape'):
        error_rates(np.zeros((2, 3)), np.zeros((2, 3)), valid=np.ones((3, 2), bool))
    with pytest.raises(ValueError, match='no pixel to evaluate'):
        error_rates(np.zeros((2, 2)), np.full((2, 2), np.nan))
