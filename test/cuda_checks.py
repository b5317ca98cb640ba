"""
The CUDA kernels against their CPU twins on small real crops (KITTI 2012 000070).

Not collected by `pytest test` (its name does not start with test_): test_cuda.py runs it in
a fresh process, under Numba's CUDA simulator (NUMBA_ENABLE_CUDASIM=1, which must be set
before numba.cuda is first imported) and on a real GPU when there is one. By hand:
    NUMBA_ENABLE_CUDASIM=1 python -m pytest -q test/cuda_checks.py
The simulator runs each GPU thread as a Python thread: the crops are tiny (24x40, D 16).
"""
from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.stereo import cost, cost_cuda, gcp, gcp_cuda, gpu, sgm, sgm_cuda
from gcp_stereo_ros.stereo.cnn import confidence, load_net
from gcp_stereo_ros.stereo.images import gray_pair, standardize
from gcp_stereo_ros.stereo.pipeline import StereoConfig, StereoPipeline
import numpy as np
import pytest
import torch

ND = 16
DEVICE = gpu.torch_device('cuda')


@pytest.fixture(scope='module')
def crop(data_dir):
    """Return a 24x40 gray pair from KITTI 2012 000070: road, a car, a pole."""
    frame = load_frame(data_dir, 'kitti2012/000070_10')
    left, right = gray_pair(frame.left, frame.right)
    return left[200:224, 520:560], right[200:224, 520:560]


@pytest.fixture(scope='module')
def cnn(crop):
    """Return the CNN confidence (cof_c, cof_d, cof_dr) of the crop, from the CPU path."""
    return confidence(load_net(), *crop, ND)


def on_gpu(*arrays):
    return [torch.from_numpy(np.ascontiguousarray(a)).to(DEVICE) for a in arrays]


def host(tensor):
    return tensor.cpu().numpy()


@pytest.mark.parametrize('kind, scale, dtype', [
    ('census', 10, np.uint16), ('census', 1, np.float32), ('sad', 1, np.float32)])
def test_cuda_cost_volume(crop, kind, scale, dtype):
    want = cost.cost_volume(*crop, ND, kind, 9, scale=scale, dtype=dtype)
    images = crop if kind == 'census' else [standardize(g) for g in crop]
    got = host(cost_cuda.cost_volume(on_gpu(np.stack(images))[0], ND, kind, 9, scale=scale,
                                     dtype=dtype))
    assert got.dtype == want.dtype
    if kind == 'census':
        np.testing.assert_array_equal(got, want)
    else:  # another summation order than the CPU's sliding window sums
        np.testing.assert_allclose(got, want, atol=2e-6)
        assert (got < cost.SAD_MAX).mean() > 0.3  # valid cells, not only the cap


@pytest.mark.parametrize('lr_check', [False, True])
def test_cuda_gcp_refinement(crop, cnn, lr_check):
    volume = cost.cost_volume(*crop, ND, 'census', 9, scale=10, dtype=np.uint16)
    want_gcp = gcp.select(*cnn, 0.6, lr_check)
    assert 0 < want_gcp.mean() < 1
    want = gcp.refine(volume.copy(), want_gcp, cnn[1], 2000, 13)
    got, *conf = on_gpu(volume, *cnn)
    got_gcp = gcp_cuda.select_refine(got, *conf, 0.6, 2000, 13, lr_check)
    np.testing.assert_array_equal(host(got_gcp), want_gcp)
    np.testing.assert_array_equal(host(got), want)


@pytest.mark.parametrize('paths, kind', [
    (4, 'census'), (8, 'census'), (16, 'census'), (16, 'sad')])
def test_cuda_sgm_and_wta(crop, paths, kind):
    """
    Check SGM and WTA against the CPU's.

    uint16 Census path sums are exact; float32 SAD ones agree within rounding (measured
    2.7e-5 at most: the CPU's compiler reassociates); the WTA on the same sums is exact.
    """
    if kind == 'census':
        volume, p1, p2, top = cost.cost_volume(*crop, ND, scale=10, dtype=np.uint16), 40, 640, 800
    else:
        volume, p1, p2, top = cost.cost_volume(*crop, ND, 'sad'), 0.3, 1.7, None
    want = sgm.aggregate(volume, p1, p2, paths)
    total = sgm_cuda.aggregate(on_gpu(volume)[0], p1, p2, paths, top)
    if kind == 'census':
        np.testing.assert_array_equal(host(total), want)
    else:
        np.testing.assert_allclose(host(total), want, rtol=1e-5)
    for subpixel, lr_check in ((False, False), (True, True)):
        got = [host(a) for a in sgm_cuda.winners(total, subpixel, lr_check)]
        for a, b in zip(got, sgm.winners(host(total), subpixel, lr_check)):
            np.testing.assert_array_equal(a, b)
        assert (~got[1]).any() == lr_check and np.isfinite(got[3]).all()


def test_cuda_pipeline_equals_cpu(crop, cnn):
    """
    Check the whole pipeline on the device against the CPU's.

    With the same confidence, the uint16 Census path (the paper's C_low 1.3, scale 10) is
    exact, float32 SAD within its rounding; with its own CNN run, the confidences agree
    within float rounding.
    """
    for kind, paths in (('census', 16), ('sad', 8)):
        cfg = StereoConfig.for_cost(kind, 'paper', max_disp=ND, paths=paths, bf16=False,
                                    gcp_lr_check=True, subpixel=True)
        cpu = StereoPipeline(cfg)(*crop, confidence=cnn)
        pipe = StereoPipeline(cfg.replace(device='cuda'))
        result = pipe(*crop, confidence=cnn)
        np.testing.assert_array_equal(result.gcp, cpu.gcp)
        if kind == 'census':
            np.testing.assert_array_equal(result.disparity, cpu.disparity)
        else:  # SAD costs round differently: the last bits, and near-ties (2 of 960 here)
            assert np.mean(~np.isclose(result.disparity, cpu.disparity, atol=1e-4)) < 0.01
        assert {'upload', 'cost', 'refine', 'sgm', 'wta', 'download'} <= set(result.seconds)
    own = pipe.with_config(StereoConfig.for_cost('census', max_disp=ND, paths=4, bf16=False,
                                                 device='cuda'))(*crop)
    np.testing.assert_allclose(own.cof_c, cnn[0], atol=2e-5)  # as in test_cnn
    assert np.mean(own.cof_d != cnn[1]) < 0.01
    assert {'cnn', 'confidence'} <= set(own.seconds)


def test_cuda_pipeline_downsample(crop):
    left, right = (np.repeat(np.repeat(g, 2, 0), 2, 1) for g in crop)  # 48x80, bins to crop
    cfg = StereoConfig.for_cost('census', use_gcp=False, max_disp=2 * ND, paths=4,
                                downsample=2)
    want = StereoPipeline(cfg)(left, right).disparity
    got = StereoPipeline(cfg.replace(device='cuda'))(left, right).disparity
    np.testing.assert_array_equal(got, want)


def test_cuda_device_errors():
    with pytest.raises(ValueError, match='cuda:7'):
        StereoPipeline(StereoConfig(device='cuda:7'))
