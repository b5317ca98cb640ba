"""Every shared pair loads with the right names, shapes, scales and masks."""
from gcp_stereo_ros.evaluation.datasets import Frame, list_frames, load_frame, load_frames
from gcp_stereo_ros.stereo.images import to_gray
import numpy as np
import pytest

# name: (height, width, colour, max_disp, largest GT disparity, valid fraction range)
EXPECTED = {
    'kitti2012/000070_10': (376, 1241, False, 128, 31497 / 256, (0.25, 0.33)),
    'middlebury2003/cones': (375, 450, True, 64, 220 / 4, (0.9, 1.0)),
    'middlebury2006/fullsize_opencv-doc/Aloe': (1110, 1282, True, 224, 211.0, (0.9, 1.0)),
    'middlebury2006/halfsize/Cloth3': (555, 626, True, 96, 166 / 2, (0.9, 1.0)),
    'middlebury_v2/cones': (375, 450, True, 64, 220 / 4, (0.75, 0.95)),
    'middlebury_v2/teddy': (375, 450, True, 64, 211 / 4, (0.75, 0.95)),
    'middlebury_v2/tsukuba': (288, 384, True, 16, 224 / 16, (0.7, 0.95)),
    'middlebury_v2/venus': (383, 434, True, 32, 158 / 8, (0.75, 0.95)),
    'motorcycle': (500, 741, True, 64, None, (0.85, 0.99)),
}
# Further shared frames, listed but not loaded here (road scenes and third-size Middlebury).
KITTI2015 = [f'kitti2015/{i:06d}_10' for i in (*range(1, 41), 45, 62, 146)]
THIRDSIZE = [f'middlebury2006/thirdsize/{s}' for s in (
    'Baby1', 'Baby2', 'Baby3', 'Bowling1', 'Bowling2', 'Cloth1', 'Cloth2', 'Cloth4',
    'Flowerpots', 'Lampshade1', 'Lampshade2', 'Monopoly')]


@pytest.fixture(scope='module')
def frames(data_dir):
    loaded = {f.name: f for f in load_frames(data_dir)}
    loaded['motorcycle'] = load_frame('motorcycle', 'motorcycle')
    return loaded


def test_names(data_dir):
    assert list_frames(data_dir) == sorted({*EXPECTED, *KITTI2015, *THIRDSIZE} - {'motorcycle'})
    assert list_frames('motorcycle') == ['motorcycle']
    assert list_frames(data_dir / 'kitti2012') == ['kitti2012/000070_10']
    assert list_frames(data_dir / 'kitti2012' / 'training') == ['training/000070_10']
    assert list_frames(data_dir / 'middlebury_v2') == ['cones', 'teddy', 'tsukuba', 'venus']
    assert list_frames(data_dir / 'middlebury_v2' / 'cones') == ['cones']
    assert load_frame(data_dir / 'middlebury2006', 'halfsize/Cloth3').max_disp == 96


@pytest.mark.parametrize('name', sorted(EXPECTED))
def test_frame(frames, name):
    h, w, colour, max_disp, gt_max, (lo, hi) = EXPECTED[name]
    f = frames[name]
    assert isinstance(f, Frame) and f.name == name
    shape = (h, w, 3) if colour else (h, w)
    assert f.left.shape == f.right.shape == shape
    assert f.left.dtype == f.right.dtype == np.uint8
    assert f.gt.shape == f.valid.shape == (h, w)
    assert f.gt.dtype == np.float32 and f.valid.dtype == bool
    assert f.max_disp == max_disp and max_disp % 16 == 0
    if gt_max is not None:
        assert np.nanmax(f.gt) == pytest.approx(gt_max)
    assert np.nanmax(f.gt) < max_disp
    assert np.isfinite(f.gt[f.valid]).all() and (f.gt[f.valid] > 0).all()
    assert lo < f.valid.mean() < hi


@pytest.mark.parametrize('name', sorted(EXPECTED))
def test_gt_warps_right_onto_left(frames, name):
    """Sampling the right image at x - gt reproduces the left far better than x does."""
    f = frames[name]
    left, right = to_gray(f.left), to_gray(f.right)
    ys, xs = np.nonzero(f.valid)
    xr = xs - f.gt[ys, xs]
    keep = xr >= 0
    ys, xs, xr = ys[keep], xs[keep], xr[keep]
    x0 = np.minimum(np.floor(xr).astype(int), right.shape[1] - 2)
    a = xr - x0
    warped = (1 - a) * right[ys, x0] + a * right[ys, x0 + 1]
    with_gt = np.abs(left[ys, xs] - warped).mean()
    with_zero = np.abs(left[ys, xs] - right[ys, xs]).mean()
    assert with_gt * 2 < with_zero, (with_gt, with_zero)


def test_right_ground_truth(frames):
    for name, gt_max in (('middlebury2003/cones', 216 / 4),
                         ('middlebury2006/halfsize/Cloth3', 166 / 2)):
        f = frames[name]
        assert f.gt_right.shape == f.gt.shape and f.gt_right.dtype == np.float32
        assert np.nanmax(f.gt_right) == pytest.approx(gt_max)
    assert frames['middlebury_v2/cones'].gt_right is None


def test_kitti_calibration(frames):
    f = frames['kitti2012/000070_10']
    assert f.focal_px == pytest.approx(718.856)
    assert f.baseline_m == pytest.approx(386.1448 / 718.856)
    assert frames['middlebury_v2/cones'].focal_px is None


def test_motorcycle_unknown_is_nan(frames):
    f = frames['motorcycle']
    assert not np.isinf(f.gt).any()
    assert (np.isnan(f.gt) == ~f.valid).all()


def test_bad_sources(tmp_path, data_dir):
    with pytest.raises(ValueError, match='Middlebury v2'):
        list_frames(tmp_path)
    with pytest.raises(ValueError, match='not "motorcycle"'):
        list_frames(tmp_path / 'missing')
    with pytest.raises(ValueError, match='no frame'):
        load_frame(data_dir, 'middlebury_v2/nope')


def test_kitti2015_layout(tmp_path):
    """Colour image_2/image_3, disp_noc_0 and the 2015 calib_cam_to_cam naming."""
    from PIL import Image
    training = tmp_path / 'kitti2015' / 'training'
    rgb = np.random.default_rng(0).integers(0, 256, (4, 6, 3), dtype=np.uint8)
    disp = np.zeros((4, 6), np.uint16)
    disp[1, 2] = 5 * 256 + 128
    for sub, image in (('image_2', rgb), ('image_3', rgb), ('disp_noc_0', disp)):
        (training / sub).mkdir(parents=True)
        for stem in ('000003_10', '000003_11'):
            Image.fromarray(image).save(training / sub / f'{stem}.png')
    (training / 'calib_cam_to_cam').mkdir()
    (training / 'calib_cam_to_cam' / '000003.txt').write_text(
        'calib_time: 09-Jan-2012 13:57:47\n'
        'P_rect_02: 721.5 0 609.6 44.9 0 721.5 172.9 0.2 0 0 1 0.003\n'
        'P_rect_03: 721.5 0 609.6 -339.5 0 721.5 172.9 2.2 0 0 1 0.003\n')
    assert list_frames(tmp_path) == ['kitti2015/000003_10']
    f = load_frame(tmp_path, 'kitti2015/000003_10')
    assert f.left.shape == (4, 6, 3) and (f.left == rgb).all()
    assert f.gt[1, 2] == 5.5 and f.valid.sum() == 1 and np.isnan(f.gt[0, 0])
    assert f.max_disp == 128
    assert f.focal_px == 721.5 and f.baseline_m == pytest.approx((44.9 + 339.5) / 721.5)
