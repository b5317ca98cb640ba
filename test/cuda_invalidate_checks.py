"""
The invalidation and the normalization on the device against the host's, on real crops.

Run as cuda_checks.py (whose helpers it takes) is, by test_cuda.py: under Numba's CUDA
simulator and on a real GPU when there is one. By hand:
    NUMBA_ENABLE_CUDASIM=1 python -m pytest -q test/cuda_invalidate_checks.py
The crops are of a few thousand pixels (40x96) for the invalidation's kernels, 16x48 for
the whole pipeline.
"""
from functools import partial

from cuda_checks import host, ND, on_gpu
from gcp_stereo_ros.stereo import postprocess, sgm
from gcp_stereo_ros.stereo.cnn.network import confidence, load_net
from gcp_stereo_ros.stereo.config import StereoConfig, UNFILTERED
from gcp_stereo_ros.stereo.cuda import postprocess as postprocess_cuda
from gcp_stereo_ros.stereo.cuda.backend import CudaBackend
from gcp_stereo_ros.stereo.images import standardize
from gcp_stereo_ros.stereo.pipeline import StereoPipeline
import numpy as np
import pytest
import torch

# What the invalidation checks turn on: every test, the depth limits with KITTI 2012's camera
# (f T = 721 px x 0.54 m, no offset) at 14.4 and 21.6 px.
KITTI_CAMERA = (389.0, 0.0)
ALL_ON = {'valid_window': True, 'lr_check': True, 'uniqueness_ratio': 1.0, 'min_depth': 18.0,
          'max_depth': 27.0, 'min_confidence': 0.9, 'background_ratio': 1.1,
          'speckle_size': 100, 'speckle_range': 4, 'plain_check': 1.5}


@pytest.fixture(scope='module', params=[2.0, 1.2345], ids=['uint16', 'float32'])
def field(kitti70, request):
    """
    Return the CPU's inputs to the invalidation of a 40x96 crop (a car, a wall, D = 32).

    (cfg, disparity, consistent, margin, disparity confidence, summed costs, plain SGM's
    disparity); the summed costs uint16 (C_low 2) or float32 (C_low 1.2345).
    """
    crop = [np.ascontiguousarray(g[150:190, 300:396]) for g in kitti70]
    cfg = StereoConfig(max_disp=32, paths=4, precision='fp32', c_low=request.param, **UNFILTERED)
    pipe = StereoPipeline(cfg)
    won = pipe(*crop)
    plain = StereoPipeline(cfg.replace(use_gcp=False, subpixel=False))(*crop).disparity
    total = pipe.backend.kept['total']
    assert total.dtype == (np.uint16 if request.param == 2.0 else np.float32)
    return (cfg, won.disparity, won.consistent, won.margin, won.disparity_confidence, total,
            plain)


def invalidated(field, changes, camera=KITTI_CAMERA, without=(), device=False):
    """Return the host's (or the device's) invalidation of `field`, ALL_ON with `changes`."""
    cfg, disp, consistent, m, *inputs = field
    sure, total, plain = (None if k in without else v
                          for k, v in zip(('sure', 'total', 'plain'), inputs))
    cfg = cfg.replace(**{**ALL_ON, **changes})
    if device:
        tensors = [None if a is None else on_gpu(a)[0]
                   for a in (disp.copy(), consistent, m, sure, total, plain)]
        return host(postprocess_cuda.invalidate(*tensors[:3], cfg, camera, *tensors[3:]))
    costs = None if total is None else partial(sgm.costs_at, total)
    return postprocess.invalidate(disp.copy(), consistent, m, cfg, camera, sure, costs, plain)


@pytest.mark.parametrize('changes, camera, without', [
    ({}, KITTI_CAMERA, ()),
    ({'background_ratio': 0.0}, KITTI_CAMERA, ()),  # every pixel below min_confidence goes
    ({}, None, ('total', 'plain')),  # no camera, no costs, no plain SGM
    ({'speckle_size': 30, 'speckle_range': 1}, KITTI_CAMERA, ('sure',))])
def test_cuda_invalidate_equals_cpu(field, changes, camera, without):
    """The device's invalidation marks the same pixels NaN as the host's, every test on."""
    want = invalidated(field, changes, camera, without)
    got = invalidated(field, changes, camera, without, device=True)
    np.testing.assert_array_equal(got, want)  # NaN where NaN, the rest bit for bit
    assert 0.3 < np.isnan(want).mean() < 0.95


def test_cuda_invalidate_each_test_counts(field):
    """On this crop each test marks pixels that the others leave (so the checks see each)."""
    want = invalidated(field, {})
    for off in ({'valid_window': False}, {'lr_check': False}, {'uniqueness_ratio': 0.0},
                {'min_depth': 0.0}, {'max_depth': 0.0}, {'background_ratio': 0.0},
                {'min_confidence': 0.0}, {'speckle_size': 0}, {'plain_check': 0.0}):
        assert not np.array_equal(invalidated(field, off), want, equal_nan=True), off


def snakes(disp):
    """
    Return `disp` with three 1 px wide paths at 200 px from the left edge, on and back.

    Their disparity steps by 0.25 px and falls back by 4 (speckle_range) every 17 px; of 193
    pixels (rows 10 to 12, crossing the crop), 100 (rows 20 to 22) and 101 (30 to 32).
    """
    out = disp.copy()
    for row, back, turn in ((10, 0, 96), (20, 21, 60), (30, 20, 60)):
        out[row, :turn] = 200 + 0.25 * (np.arange(turn) % 17)
        out[row + 2, back:turn] = out[row, back:turn]
        out[row + 1, turn - 1] = out[row, turn - 1]
    return out


@pytest.mark.parametrize('field', [2.0], ids=['uint16'], indirect=True)
def test_cuda_speckles_equal_opencv(field):
    """
    Speckles on the device: cv2.filterSpeckles' regions, on cuts of a real disparity.

    The cuts cut regions at their edges; the paths are larger than speckle_size only along
    their length, and join at exactly speckle_range; rint rounds half to even.
    """
    disp, consistent = field[1:3]
    disp = np.where(consistent, disp, np.float32(np.nan))  # the left-right check's holes
    edges = kept = 0
    for y0, y1, x0, x1 in ((0, 40, 0, 96), (3, 31, 10, 50), (12, 40, 40, 96)):
        cut = np.ascontiguousarray(disp[y0:y1, x0:x1])
        for size, max_diff in ((100, 4), (20, 1), (400, 8), (5, 0.5)):
            want = postprocess.speckles(cut, size, max_diff)
            got = host(postprocess_cuda.speckles(on_gpu(cut)[0], size, max_diff))
            np.testing.assert_array_equal(got, want)
            assert want.any()
            edges += want[[0, -1]].sum() + want[:, [0, -1]].sum()
            kept += (np.isfinite(cut) & ~want).sum()
    assert edges > 50 and kept > 500  # regions the cuts' edges cut went, others stayed
    paths = snakes(disp)
    for max_diff, kept in ((4, {193, 101}), (3, set())):  # at 3 px, pieces of 17 px
        want = postprocess.speckles(paths, 100, max_diff)
        got = host(postprocess_cuda.speckles(on_gpu(paths)[0], 100, max_diff))
        np.testing.assert_array_equal(got, want)
        on = paths >= 200
        assert {int((on & ~want)[row - 1:row + 2].sum()) for row in (11, 21, 31)} - {0} == kept
    for second, joined in ((14.03125, True), (14.09375, False)):  # x 16: 224.5, 225.5
        pair_ = np.float32([[10.0, second]])
        want = postprocess.speckles(pair_, 1, 4)
        got = host(postprocess_cuda.speckles(on_gpu(pair_)[0], 1, 4))
        np.testing.assert_array_equal(got, want)
        assert not want.any() if joined else want.all()


@pytest.mark.parametrize('field', [2.0], ids=['uint16'], indirect=True)
def test_cuda_backgrounds_equal_cpu(field):
    """`fill_rows` on the device: the background of each low pixel, rows all low too."""
    disp, sure = field[1], field[4]
    low = sure < 0.9
    low[5] = True  # no pixel stays: NaN
    low[6, :3] = low[6, -3:] = True  # at the row's ends: the one pixel beside
    low[7] = False
    low[7, 40:43] = True
    want = postprocess.backgrounds(disp, low)
    got = host(postprocess_cuda.backgrounds(*on_gpu(disp, low)))
    np.testing.assert_array_equal(got, want)
    stays = (~low).any(1)[:, None]  # rows with a pixel that stays
    assert np.isnan(want[5]).all() and np.isfinite(want[low & stays]).all()


def test_cuda_standardize_equals_the_host(kitti70):
    """
    The normalization on the device: numpy's float32 mean and std within 1e-6 relative.

    The device sums in float64, numpy pairwise in float32: the standardized images agree
    within 1e-6 of their largest value.
    """
    raw, standardized = (host(a) for a in CudaBackend('cuda').upload(*kitti70, True))
    np.testing.assert_array_equal(raw, np.stack(kitti70))
    for got, gray in zip(standardized, kitti70):
        want = standardize(gray)
        assert np.abs(got - want).max() <= 1e-6 * np.abs(want).max()
    flat = np.full((5, 7), 3.0, np.float32)  # std 0: divided by 1
    np.testing.assert_array_equal(host(CudaBackend('cuda').upload(flat, flat, True)[1]), 0)
    assert CudaBackend('cuda').upload(flat, flat, False)[1] is None


def test_cuda_pipeline_invalidates_as_the_cpu(kitti70):
    """
    The pipeline invalidates on the device and downloads once: the same published pixels.

    The default Census config (uint16 volumes) with every test on and a camera, on a 16x48
    crop of disparities 10 to 12 px (depth limits at 10.2 and 11.8 px).
    """
    crop = [np.ascontiguousarray(g[184:200, 408:456]) for g in kitti70]
    cnn = confidence(load_net(), *crop, ND)
    cfg = StereoConfig(max_disp=ND, paths=4, precision='fp32', lr_check=True, min_depth=33.0,
                       max_depth=38.0, speckle_size=20)
    want = StereoPipeline(cfg)(*crop, cnn=cnn, camera=KITTI_CAMERA)
    pipe = StereoPipeline(cfg.replace(device='cuda'))
    got = pipe(*crop, cnn=cnn, camera=KITTI_CAMERA)
    assert pipe.backend.kept['total'].dtype == torch.uint16
    np.testing.assert_array_equal(got.disparity, want.disparity)
    assert 0.5 < np.isnan(want.disparity).mean() < 0.9
    np.testing.assert_allclose(got.disparity_confidence, want.disparity_confidence, atol=1e-5)
    assert (got.disparity_confidence[np.isnan(got.disparity)] == 0).all()
    for name in ('consistent', 'margin', 'gcp'):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    stages = list(got.seconds)
    assert stages.index('invalidate') < stages.index('download') == len(stages) - 1
