"""
The CUDA kernels against their CPU twins on small real crops (KITTI 2012 000070).

Not collected by `pytest test` (its name does not start with test_): test_cuda.py runs it in
a fresh process, under Numba's CUDA simulator (NUMBA_ENABLE_CUDASIM=1, which must be set
before numba.cuda is first imported) and on a real GPU when there is one. By hand:
    NUMBA_ENABLE_CUDASIM=1 python -m pytest -q test/cuda_checks.py
The simulator runs each GPU thread as a Python thread and each barrier as a wait for all of a
block's threads: the crops are tiny (16x32, D 16; the SGM checks cut 10x16 of it).
"""
from collections import Counter, defaultdict
import sys
import threading

from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.stereo import cost, gcp, sgm
from gcp_stereo_ros.stereo.cnn.network import confidence, load_net
from gcp_stereo_ros.stereo.config import StereoConfig
from gcp_stereo_ros.stereo.costs import SAD_MAX
from gcp_stereo_ros.stereo.cuda import cost as cost_cuda, gcp as gcp_cuda, gpu, sgm as sgm_cuda
from gcp_stereo_ros.stereo.images import standardize
from gcp_stereo_ros.stereo.pipeline import StereoPipeline
import numpy as np
import pytest
import torch

ND = 16
DEVICE = gpu.torch_device('cuda')
# The simulator's threads wait at a barrier until the GIL reaches each: hand it over 10x more
# often than Python's 5 ms (that halves the SGM checks' time here).
sys.setswitchinterval(5e-4)


@pytest.fixture(scope='module')
def crop(kitti70):
    """Return a 16x32 crop of KITTI 2012 000070: road, a car, a pole."""
    return [g[204:220, 524:556] for g in kitti70]


@pytest.fixture(scope='module')
def wide(kitti70):
    """Return a 12x64 crop beside it, room for D = 40."""
    return [g[204:216, 492:556] for g in kitti70]


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
        assert (got < SAD_MAX).mean() > 0.2  # valid cells (26 % here), not only the cap


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


def sgm_volume(crop, kind, nd=ND):
    """Return a Census (uint16) or SAD (float32) volume of the crop with penalties and top."""
    if kind == 'census':
        return cost.cost_volume(*crop, nd, scale=10, dtype=np.uint16), 40, 640, 800
    return cost.cost_volume(*crop, nd, 'sad'), 0.3, 1.7, None


def check_sgm_and_wta(volume, p1, p2, paths, top, options):
    """Check `cuda.sgm` against the CPU, exactly: S, and the WTA with each (subpixel, lr)."""
    want = sgm.aggregate(volume, p1, p2, paths)
    total = sgm_cuda.aggregate(on_gpu(volume)[0], p1, p2, paths, top)
    assert total.dtype == gpu.VOLUME_TYPES[volume.dtype]
    np.testing.assert_array_equal(host(total), want)
    for subpixel, lr_check in options:
        got = [host(a) for a in sgm_cuda.winners(total, subpixel, lr_check)]
        for a, b in zip(got, sgm.winners(want, subpixel, lr_check)):  # disp ... s_second
            np.testing.assert_array_equal(a, b)
        got = np.where(got[1], got[0], np.float32(np.nan))  # NaN where inconsistent
    return want, got


@pytest.mark.parametrize('paths, kind', [
    (4, 'census'), (8, 'census'), (16, 'census'), (16, 'sad')])
def test_cuda_sgm_and_wta(crop, paths, kind):
    """
    Check SGM and WTA against the CPU's on a 10x16 cut of the crop: both exact.

    float32 too: the kernel sums in the CPU's order (see `cuda.sgm`).
    """
    volume, *penalty = sgm_volume(crop, kind)
    volume = np.ascontiguousarray(volume[4:14, 16:])
    want, got = check_sgm_and_wta(volume, *penalty[:2], paths, penalty[2],
                                  ((False, False), (True, True)))
    best = np.argmin(want, axis=2)
    inside = np.arange(best.shape[1]) >= best  # x - best >= 0: a right pixel to check
    assert np.isnan(got[~inside]).all()  # a winner beyond the left edge has no right twin
    assert 0.05 < np.isnan(got[inside]).mean() < 0.75  # the left-right check marks some
    assert len(np.unique(np.argmin(want, axis=2))) > 4  # a scene, not one disparity


@pytest.mark.parametrize('nd, rows, cols', [
    (16, 4, 10),  # W < D
    (13, 4, 14),  # D not a multiple of the 16 lanes
    (40, 3, 8),  # 32 lanes, the second d of each lane partly past D; W < D
    (1, 5, 12)])  # D = 1
@pytest.mark.parametrize('kind', ['census', 'sad'])
def test_cuda_sgm_and_wta_edges(wide, nd, rows, cols, kind):
    """
    Check the lanes' edges: S and the WTA exact against the CPU on small cuts of `wide`.

    The left-right check only where D <= W + 1: beyond, the CPU's right-view scan of a pixel
    whose best d exceeds x + W reads outside S.
    """
    volume, *penalty = sgm_volume(wide, kind, nd)
    volume = np.ascontiguousarray(volume[4:4 + rows, 64 - cols:])
    lr = nd <= cols + 1
    check_sgm_and_wta(volume, *penalty[:2], 16, penalty[2], ((True, lr), (False, False)))


class Recorded:
    """Count the 32-byte sectors that each warp's load of a simulated array touches."""

    def __init__(self, array):
        from numba.cuda.simulator.cudadrv.devicearray import FakeCUDAArray

        reads = self.reads = []

        class Logged(FakeCUDAArray):

            def __getitem__(self, index):
                t = threading.current_thread()  # a simulated GPU thread
                offset = np.ravel_multi_index(index, self.shape, 'wrap') * self.dtype.itemsize
                reads.append((tuple(t.blockIdx), t.thread_id, index[:-1], offset))
                return super().__getitem__(index)

        self.array = Logged(array)

    def warp_loads(self):
        """
        Return [(lanes, sectors)] of each warp-wide load.

        A load: the reads of one warp (32 threads of a block) at the n-th time each thread
        reads that pixel (all but the d index), the lanes' loads of one instruction.
        """
        seen, loads = Counter(), defaultdict(list)
        for block, tid, pixel, offset in self.reads:
            n = seen[block, tid, pixel]
            seen[block, tid, pixel] += 1
            loads[block, tid // 32, pixel, n].append(offset // 32)
        return [(len(s), len(set(s))) for s in loads.values()]


@pytest.mark.parametrize('dtype', [np.uint16, np.float32])
def test_cuda_sgm_and_wta_loads_are_coalesced(monkeypatch, dtype):
    """
    Count the sectors of every warp load of the volumes in the SGM and WTA kernels.

    At D = 64 (32 lanes) a warp reads 32 neighbouring d of one pixel: 64 bytes of uint16
    (2 sectors) or 128 of float32 (4); the right view's winners read consecutive d that start
    anywhere (one sector more). One thread per path, as before, read 32 sectors a load.
    """
    rng = np.random.default_rng(1)
    volume = torch.from_numpy(rng.integers(0, 100, (3, 6, 64)).astype(dtype))
    wide = rng.integers(10, 100, (1, 80, 64)).astype(dtype)
    wide[0, np.arange(80), np.arange(80) % 8] = 0  # best d <= x: the check reads the right WTA
    wide = torch.from_numpy(wide)
    logs = []
    view = gpu.view

    def logged(tensor):
        if tensor is volume or tensor is wide:
            logs.append(Recorded(tensor.numpy()))
            return logs[-1].array
        return view(tensor)

    monkeypatch.setattr(gpu, 'view', logged)
    sgm_cuda.aggregate(volume, 3, 20, 4, 100)
    sgm_cuda.winners(wide, True, True)
    size = np.dtype(dtype).itemsize
    assert len(logs) == 3  # _paths, _right_winners, _winners
    for kernel, log in zip(('paths', 'right winners', 'winners'), logs):
        loads = log.warp_loads()
        together = [(lanes, sectors) for lanes, sectors in loads if lanes > 1]
        assert sum(lanes for lanes, _ in together) > 0.95 * len(log.reads), kernel
        # Contiguous: the fewest sectors the lanes' bytes fit in, one more where unaligned.
        assert all(sectors <= -(-lanes * size // 32) + 1 for lanes, sectors in together), kernel
        full = Counter(sectors for lanes, sectors in loads if lanes == 32)
        assert sum(full.values()) > 20, kernel
        if kernel == 'right winners':
            assert set(full) <= {size, size + 1}, full
        else:
            assert set(full) == {size}, (kernel, full)


def test_cuda_pipeline_equals_cpu(crop, cnn):
    """
    Check the whole pipeline on the device against the CPU's.

    With the same confidence, the uint16 Census path (the paper's C_low 1.3, scale 10) is
    exact, float32 SAD within its rounding; with its own CNN run, the confidences agree
    within float rounding.
    """
    for kind, paths in (('census', 16), ('sad', 8)):
        cfg = StereoConfig.for_cost(kind, 'paper', max_disp=ND, paths=paths, precision='fp32',
                                    gcp_lr_check=True, subpixel=True)
        on_cpu = StereoPipeline(cfg)
        cpu = on_cpu(*crop, cnn=cnn)
        pipe = StereoPipeline(cfg.replace(device='cuda'))
        result = pipe(*crop, cnn=cnn)
        np.testing.assert_array_equal(result.gcp, cpu.gcp)
        kept = on_cpu.backend.kept['total']  # the path sums of the pair
        got, want = host(pipe.backend.kept['total']), kept  # the background test reads them
        switched = on_cpu.with_config(cfg.replace(device='cuda'))  # a live switch
        switched(*crop, cnn=cnn)
        assert switched.backend is not on_cpu.backend  # the CPU's buffers stay the CPU's
        assert on_cpu.backend.kept['total'] is kept and 'total' in switched.backend.kept
        assert got.dtype == want.dtype
        if kind == 'census':
            np.testing.assert_array_equal(result.disparity, cpu.disparity)
            np.testing.assert_array_equal(got, want)
            # computed on the device (disparity_confidence_cuda): box means round differently
            np.testing.assert_allclose(result.disparity_confidence, cpu.disparity_confidence,
                                       atol=1e-5, rtol=0)
            assert 'disparity_confidence' in result.seconds
        else:  # SAD costs round differently: the last bits, and near-ties (flips at SAD near-ties)
            assert np.mean(~np.isclose(result.disparity, cpu.disparity, atol=1e-4)) < 0.01
            np.testing.assert_allclose(got, want, rtol=1e-5)
        assert {'upload', 'cost', 'refine', 'sgm', 'wta', 'invalidate', 'download'} <= set(
            result.seconds)
    # plain SGM for gcp_plain_check and plain_check, into the path sums the GCPs' SGM reuses
    cfg = StereoConfig.for_cost('census', 'paper', max_disp=ND, paths=4, precision='fp32',
                                plain_check=1.0, gcp_plain_check=True)
    cpu = StereoPipeline(cfg)(*crop, cnn=cnn)
    result = pipe.with_config(cfg.replace(device='cuda'))(*crop, cnn=cnn)
    np.testing.assert_array_equal(result.gcp, cpu.gcp)
    np.testing.assert_array_equal(result.disparity, cpu.disparity)
    assert np.isnan(cpu.disparity).mean() > 0.001 and 'plain_sgm' in result.seconds
    unchecked = StereoPipeline(cfg.replace(gcp_plain_check=False))(*crop, cnn=cnn)
    assert cpu.gcp.sum() < unchecked.gcp.sum()
    own_cnn = pipe.with_config(StereoConfig.for_cost('census', max_disp=ND, paths=4,
                                                     precision='fp32', cnn_filter_radius=0,
                                                     device='cuda'))
    own = own_cnn(*crop, timed=True)
    np.testing.assert_allclose(own.cof_c, cnn[0], atol=2e-5)  # as in test_cnn
    assert np.mean(own.cof_d != cnn[1]) < 0.01
    assert {'cnn', 'confidence'} <= set(own.seconds)
    untimed = own_cnn(*crop)  # the node's way: nothing waits for the device
    assert not {'cnn', 'confidence'} & set(untimed.seconds)
    np.testing.assert_array_equal(untimed.disparity, own.disparity)
    # with the CNN's guided filter (as in test_cnn_filter: near-ties may flip)
    cfg = StereoConfig(max_disp=ND, paths=4, precision='fp32', cnn_filter_radius=4)
    filtered = pipe.with_config(cfg.replace(device='cuda'))(*crop)
    want = confidence(load_net(), *crop, ND, radius=cfg.cnn_filter_radius)
    np.testing.assert_allclose(filtered.cof_c, want[0], atol=1e-3)
    assert np.mean(np.abs(filtered.cof_d - want[1]) > 1) < 0.01


def test_cuda_pipeline_downsample(crop):
    left, right = (np.repeat(np.repeat(g, 2, 0), 2, 1) for g in crop)  # 32x64, bins to crop
    cfg = StereoConfig.for_cost('census', use_gcp=False, max_disp=2 * ND, paths=4,
                                downsample=2)
    want = StereoPipeline(cfg)(left, right).disparity
    got = StereoPipeline(cfg.replace(device='cuda'))(left, right).disparity
    np.testing.assert_array_equal(got, want)


def test_cuda_pipeline_median(crop, cnn):
    """The 3x3 median on the device picks what cv2.medianBlur picks, edges included."""
    cfg = StereoConfig.for_cost('census', max_disp=ND, paths=4, median=True, subpixel=True,
                                valid_window=False, speckle_size=0)
    want = StereoPipeline(cfg)(*crop, cnn=cnn)
    got = StereoPipeline(cfg.replace(device='cuda'))(*crop, cnn=cnn)
    np.testing.assert_array_equal(got.disparity, want.disparity)
    np.testing.assert_allclose(got.disparity_confidence, want.disparity_confidence, atol=1e-5)


def test_cuda_device_errors():
    with pytest.raises(ValueError, match='cuda:7'):
        StereoPipeline(StereoConfig(device='cuda:7'))


# On a GPU only (the simulator would take hours): whole frames, the defaults in fp32, with the
# CPU's CNN outputs, publish the same pixels (the disparity confidence rounds differently on the
# device: a pixel at min_confidence may flip, and with it a speckle).
GPU_FRAMES = ['kitti2012/000070_10'] + [f'kitti2015/{n:06d}_10' for n in range(31, 41)]


@pytest.mark.parametrize('name', GPU_FRAMES)
def test_gpu_publishes_the_cpus_pixels_on_whole_frames(data_dir, name):
    frame = load_frame(data_dir, name)
    cfg = StereoConfig(max_disp=frame.max_disp, precision='fp32')
    cpu = StereoPipeline(cfg)(frame.left, frame.right)
    result = StereoPipeline(cfg.replace(device='cuda'))(frame.left, frame.right, cnn=cpu.cnn)
    np.testing.assert_array_equal(result.gcp, cpu.gcp)
    differ = ~((result.disparity == cpu.disparity)
               | (np.isnan(result.disparity) & np.isnan(cpu.disparity)))
    assert differ.mean() < 1e-4, f'{name}: {differ.sum()} pixels differ'
