"""SGM: exact agreement with a brute-force reference, and the optional post-processing."""
from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.stereo.cost import cost_volume
from gcp_stereo_ros.stereo.images import gray_pair
from gcp_stereo_ros.stereo.sgm import aggregate, directions, winners
import numpy as np
import pytest


def reference_aggregate(cost, p1, p2, paths):
    """Plain recursion over each path, straight from the SGM equations."""
    h, w, nd = cost.shape
    total = np.zeros(cost.shape)
    for dx, dy in directions(paths):
        for rx, ry in ((dx, dy), (-dx, -dy)):
            lr = {}

            def path_cost(y, x):
                if (y, x) not in lr:
                    py, px = y - ry, x - rx
                    if 0 <= py < h and 0 <= px < w:
                        prev = path_cost(py, px)
                        m = prev.min()
                        out = np.empty(nd)
                        for d in range(nd):
                            best = min(prev[d], m + p2)
                            if d > 0:
                                best = min(best, prev[d - 1] + p1)
                            if d < nd - 1:
                                best = min(best, prev[d + 1] + p1)
                            out[d] = cost[y, x, d] + best - m
                        lr[y, x] = out
                    else:
                        lr[y, x] = cost[y, x].astype(float)
                return lr[y, x]

            for y in range(h):
                for x in range(w):
                    total[y, x] += path_cost(y, x)
    return total


@pytest.mark.parametrize('dtype', [np.float32, np.uint16])
@pytest.mark.parametrize('paths', [4, 8, 16])
@pytest.mark.parametrize('shape', [(7, 11, 5), (9, 6, 1), (1, 8, 4), (5, 1, 3)])
def test_aggregate_equals_reference(paths, shape, dtype):
    rng = np.random.default_rng(sum(shape) + paths)
    cost = rng.integers(0, 40, size=shape).astype(dtype)
    got = aggregate(cost, 3, 17, paths)
    want = reference_aggregate(cost, 3, 17, paths)
    assert got.dtype == dtype
    np.testing.assert_array_equal(got, want.astype(dtype))
    # WTA takes the first minimum on ties, as np.argmin does.
    np.testing.assert_array_equal(winners(got)[0], np.argmin(want, axis=2).astype(np.float32))


@pytest.mark.parametrize('paths', [8, 16])
def test_real_census_volume_equals_reference(data_dir, paths):
    # The pipeline's default volume type on a real scene (KITTI 2015 000031: road, cars): a
    # 20x64 crop, wide enough for the sweeps' column bands and the knight-move paths to cross
    # between them, with the bench's penalties.
    frame = load_frame(data_dir / 'kitti2015', 'kitti2015/000031_10')
    left, right = gray_pair(frame.left, frame.right)
    cost = cost_volume(left[180:200, 600:664], right[180:200, 600:664], 24, 'census',
                       dtype=np.uint16)
    assert cost.max() > 20 and len(np.unique(cost)) > 20
    want = reference_aggregate(cost, 4, 128, paths)
    np.testing.assert_array_equal(aggregate(cost, 4, 128, paths), want)
    np.testing.assert_array_equal(aggregate(cost.astype(np.float32), 4, 128, paths), want)


def test_uint16_sums_up_to_the_limit_are_exact():
    # Costs (0, 1000, 1000) everywhere, P1 1500, P2 3000, 16 paths: L_r reaches C + P2 = 4000
    # on every path inside the image, so S hits the bound 16 * 4000 = 64000 (of 65535), and
    # L + P1, L + P2 go past 32767 too; any 16-bit wrap-around would show.
    cost = np.tile(np.array([0, 1000, 1000]), (15, 15, 1))
    got = aggregate(cost.astype(np.uint16), 1500, 3000, 16)
    want = reference_aggregate(cost, 1500, 3000, 16)
    assert want.max() == 64000
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(winners(got)[0], np.argmin(want, axis=2).astype(np.float32))
    with pytest.raises(ValueError, match='overflow'):
        aggregate(cost.astype(np.uint16), 1500, 3100, 16)
    with pytest.raises(ValueError, match='integer penalties'):
        aggregate(cost.astype(np.uint16), 1.5, 30, 16)


def test_paths_and_penalties_validated():
    cost = np.zeros((4, 4, 3), np.float32)
    with pytest.raises(ValueError, match='paths'):
        aggregate(cost, 1, 2, paths=6)
    with pytest.raises(ValueError, match='P1'):
        aggregate(cost, 5, 2)
    with pytest.raises(ValueError, match='shape'):
        aggregate(np.zeros((4, 4), np.float32), 1, 2)


@pytest.mark.parametrize('bad', [-1.0, np.nan, np.inf])
def test_negative_or_non_finite_costs_rejected(bad):
    cost = np.zeros((4, 5, 3), np.float32)
    cost[2, 3, 1] = bad
    with pytest.raises(ValueError, match='1 cells that are negative, NaN or infinite'):
        aggregate(cost, 1, 2)
    with pytest.raises(ValueError, match='1 cells that are negative, NaN or infinite'):
        winners(cost)
