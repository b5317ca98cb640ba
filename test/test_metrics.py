"""Error rates on a hand-made case with known answers."""
from gcp_stereo_ros.evaluation.metrics import error_rates
import numpy as np
import pytest


def test_hand_made_case():
    gt = np.array([[10.0, 10.0, 10.0, 10.0],
                   [10.0, 10.0, np.nan, 10.0]])
    disp = np.array([[10.5, 11.5, 12.5, 14.0],
                     [16.0, np.nan, 0.0, np.inf]])
    # errors at the 6 evaluated pixels: 0.5, 1.5, 2.5, 4, 6, none (NaN), and one more none (inf)
    r = error_rates(disp, gt)
    assert r['bad1'] == pytest.approx(100 * 6 / 7)
    assert r['bad2'] == pytest.approx(100 * 5 / 7)
    assert r['bad3'] == pytest.approx(100 * 4 / 7)
    assert r['bad5'] == pytest.approx(100 * 3 / 7)
    assert r['mae'] == pytest.approx((0.5 + 1.5 + 2.5 + 4 + 6) / 5)
    assert set(r) == {'bad1', 'bad2', 'bad3', 'bad5', 'mae'}


def test_valid_mask_restricts_evaluation():
    gt = np.array([[1.0, 2.0, 3.0]])
    disp = np.array([[1.0, 9.0, np.nan]])
    r = error_rates(disp, gt, valid=np.array([[True, False, True]]))
    assert r['bad1'] == pytest.approx(50.0)
    assert r['mae'] == 0.0
    r = error_rates(disp, gt, valid=np.array([[False, False, True]]))
    assert r['bad5'] == 100.0 and np.isnan(r['mae'])


def test_perfect_estimate():
    gt = np.linspace(0, 60, 20).reshape(4, 5)
    assert error_rates(gt, gt) == {'bad1': 0.0, 'bad2': 0.0, 'bad3': 0.0, 'bad5': 0.0, 'mae': 0.0}


def test_bad_input():
    with pytest.raises(ValueError, match='shape'):
        error_rates(np.zeros((2, 3)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match='valid mask has shape'):
        error_rates(np.zeros((2, 3)), np.zeros((2, 3)), valid=np.ones((3, 2), bool))
    with pytest.raises(ValueError, match='no pixel to evaluate'):
        error_rates(np.zeros((2, 2)), np.full((2, 2), np.nan))
