"""Cost volumes: the census definition, SAD against a box filter, invalid cells, bad input."""
import cv2
from gcp_stereo_ros.stereo.cost import census_transform, cost_volume
from gcp_stereo_ros.stereo.costs import SAD_MAX
from gcp_stereo_ros.stereo.images import gray_pair, standardize
import numpy as np
import pytest
from skimage import data


@pytest.fixture(scope='module')
def motorcycle():
    left, right, _ = data.stereo_motorcycle()
    return left[100:220, 200:420], right[100:220, 200:420]


def census_reference(gray, y, x, rad=4):
    """Return one pixel's bit string, written out: bit k = neighbour k darker than the centre."""
    bits = [gray[y + dy, x + dx] < gray[y, x]
            for dy in range(-rad, rad + 1) for dx in range(-rad, rad + 1) if (dy, dx) != (0, 0)]
    return sum(int(b) << k for k, b in enumerate(bits))


def test_census_transform_matches_definition(motorcycle):
    gray, _ = gray_pair(*motorcycle)
    ct = census_transform(gray)
    rng = np.random.default_rng(0)
    for y, x in zip(rng.integers(4, gray.shape[0] - 4, 200),
                    rng.integers(4, gray.shape[1] - 4, 200)):
        got = int(ct[0, y, x]) | (int(ct[1, y, x]) << 64)
        assert got == census_reference(gray, y, x)


def test_census_cost_is_hamming_distance(motorcycle):
    left, right = gray_pair(*motorcycle)
    vol = cost_volume(left, right, 32, 'census')
    assert vol.shape == left.shape + (32,) and vol.dtype == np.float32
    assert vol.min() == 0 and vol.max() == 80
    rng = np.random.default_rng(1)
    for y, x, d in zip(rng.integers(4, 116, 100), rng.integers(40, 216, 100),
                       rng.integers(0, 32, 100)):
        want = bin(census_reference(left, y, x) ^ census_reference(right, y, x - d)).count('1')
        assert vol[y, x, d] == want
    # Invalid cells: windows leaving either image, and x - d left of the right window.
    assert (vol[:4] == 80).all() and (vol[:, -4:] == 80).all()
    assert (vol[10, 10, 7:] == 80).all() and (vol[10, 10, :7] < 80).any()


def test_uint16_census_is_scaled_hamming_distance(motorcycle):
    left, right = gray_pair(*motorcycle)
    vol = cost_volume(left, right, 32, 'census')
    fixed = cost_volume(left, right, 32, 'census', scale=10, dtype=np.uint16)
    assert fixed.dtype == np.uint16
    np.testing.assert_array_equal(fixed, vol * 10)
    np.testing.assert_array_equal(cost_volume(left, right, 32, 'census', dtype=np.uint16), vol)
    with pytest.raises(ValueError, match=r'integer costs only \(sad costs are fractional\)'):
        cost_volume(left, right, 32, 'sad', dtype=np.uint16)
    with pytest.raises(ValueError, match='16 bits'):
        cost_volume(left, right, 32, 'census', scale=1000, dtype=np.uint16)  # 80000 > 65535
    with pytest.raises(ValueError, match='scale'):
        cost_volume(left, right, 32, 'census', scale=0)
    with pytest.raises(ValueError, match='dtype'):
        cost_volume(left, right, 32, 'census', dtype=np.int32)


def test_sad_is_standardized_window_mean(motorcycle):
    left, right = gray_pair(*motorcycle)
    vol = cost_volume(left, right, 24, 'sad')
    ls, rs = standardize(left), standardize(right)
    for d in (0, 5, 23):
        diff = np.abs(ls[:, d:] - rs[:, :rs.shape[1] - d])
        box = np.minimum(cv2.blur(diff, (9, 9)), SAD_MAX)
        np.testing.assert_allclose(vol[4:-4, d + 8:-4, d], box[4:-4, 8:-4], atol=1e-4)
    assert vol.max() == np.float32(SAD_MAX) and vol.min() >= 0
    # Truncation at 3.2 is rare on real images: almost every valid cell lies below it.
    valid = vol[4:-4, 4 + 24:-4]
    assert (valid >= SAD_MAX).mean() < 0.01


def test_rgb_and_integer_inputs_agree(motorcycle):
    left, right = motorcycle
    a = cost_volume(left, right, 16, 'census')
    lg, rg = gray_pair(left, right)
    b = cost_volume((lg * 257).astype(np.uint16), (rg * 257).astype(np.uint16), 16, 'census')
    assert (a != b).mean() < 0.01  # uint16 rounding flips a few ties only


@pytest.mark.parametrize('left, right, message', [
    (np.zeros((10, 12)), np.zeros((10, 13)), 'one size'),
    (np.zeros((10, 12, 2)), np.zeros((10, 12, 2)), 'shape'),
    (np.zeros((0, 12)), np.zeros((0, 12)), 'empty'),
    (np.full((10, 12), np.nan), np.zeros((10, 12)), 'NaN'),
    (np.zeros((10, 12), bool), np.zeros((10, 12), bool), 'dtype'),
])
def test_bad_input_is_explained(left, right, message):
    with pytest.raises(ValueError, match=message):
        cost_volume(left, right, 4)


def test_bad_parameters_are_explained(motorcycle):
    with pytest.raises(ValueError, match='max_disp'):
        cost_volume(*motorcycle, 0)
    with pytest.raises(ValueError, match='window'):
        cost_volume(*motorcycle, 8, window=8)
    with pytest.raises(ValueError, match='cost'):
        cost_volume(*motorcycle, 8, cost='ncc')
