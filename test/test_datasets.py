"""Every shared pair loads with the right names, shapes, scales and masks."""
from pathlib import Path

from gcp_stereo_ros.evaluation.datasets import Frame, list_frames, load_frame, load_frames
from gcp_stereo_ros.stereo.images import to_gray
import numpy as np
from PIL import Image
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
    # MiddEval3: Teddy (half size) has no calib.txt and no mask, Motorcycle (quarter) both
    'middeval3/MiddEval3/trainingH/Teddy': (750, 900, True, 112, 106.0, (0.95, 0.99)),
    'middeval3/MiddEval3/trainingQ/Motorcycle': (497, 741, True, 80, 62.87735, (0.8, 0.9)),
    'motorcycle': (500, 741, True, 64, None, (0.85, 0.99)),
}
# Further shared frames, listed but not loaded here (road scenes and third-size Middlebury).
KITTI2015 = [f'kitti2015/{i:06d}_10' for i in (*range(1, 41), 45, 62, 146)]
THIRDSIZE = [f'middlebury2006/thirdsize/{s}' for s in (
    'Baby1', 'Baby2', 'Baby3', 'Bowling1', 'Bowling2', 'Cloth1', 'Cloth2', 'Cloth4',
    'Flowerpots', 'Lampshade1', 'Lampshade2', 'Monopoly')]


@pytest.fixture(scope='module')
def frames(data_dir):
    loaded = {f.name: f for f in load_frames(data_dir, sorted(set(EXPECTED) - {'motorcycle'}))}
    loaded['motorcycle'] = load_frame('motorcycle', 'motorcycle')
    return loaded


def test_names(data_dir):
    assert list_frames(data_dir) == sorted({*EXPECTED, *KITTI2015, *THIRDSIZE} - {'motorcycle'})
    assert list_frames('motorcycle') == ['motorcycle']
    assert list_frames(data_dir / 'kitti2012') == ['kitti2012/000070_10']
    assert list_frames(data_dir / 'kitti2012' / 'training') == ['training/000070_10']
    assert list_frames(data_dir / 'middlebury_v2') == ['cones', 'teddy', 'tsukuba', 'venus']
    assert list_frames(data_dir / 'middlebury_v2' / 'cones') == ['cones']
    assert list_frames(data_dir / 'middeval3') == ['MiddEval3/trainingH/Teddy',
                                                   'MiddEval3/trainingQ/Motorcycle']
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
                         ('middlebury2006/halfsize/Cloth3', 166 / 2),
                         ('middeval3/MiddEval3/trainingQ/Motorcycle', 62.880585)):
        f = frames[name]
        assert f.gt_right.shape == f.gt.shape and f.gt_right.dtype == np.float32
        assert np.nanmax(f.gt_right) == pytest.approx(gt_max)
    assert frames['middlebury_v2/cones'].gt_right is None
    assert frames['middeval3/MiddEval3/trainingH/Teddy'].gt_right is None


def test_kitti_calibration(frames):
    f = frames['kitti2012/000070_10']
    assert f.focal_px == pytest.approx(718.856)
    assert f.baseline_m == pytest.approx(386.1448 / 718.856)
    assert f.principal_px == pytest.approx((607.1928, 185.2157)) and f.doffs_px == 0
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
    assert f.principal_px == (609.6, 172.9) and f.doffs_px == 0


MIDDEVAL3 = Path('middeval3/MiddEval3')


def test_middeval3_masks_and_notes(frames, data_dir):
    """Scored on mask0nocc == 255 where shipped; without mask or ndisp, the frame says so."""
    moto = frames[str(MIDDEVAL3 / 'trainingQ/Motorcycle')]
    mask = np.array(Image.open(data_dir / MIDDEVAL3 / 'trainingQ/Motorcycle/mask0nocc.png'))
    assert (moto.valid == (np.isfinite(moto.gt) & (mask == 255))).all()
    assert np.isfinite(moto.gt).mean() - moto.valid.mean() > 0.1  # occlusions left out
    assert moto.note is None and moto.max_disp == 80  # calib.txt: ndisp=70
    teddy = frames[str(MIDDEVAL3 / 'trainingH/Teddy')]
    assert (teddy.valid == np.isfinite(teddy.gt)).all()
    assert 'no mask0nocc.png' in teddy.note and 'no ndisp' in teddy.note
    assert all(frames[n].note is None for n in EXPECTED if 'middeval3' not in n)


def scene_copy(tmp_path, data_dir, names, calib=None):
    """Make a MiddEval3 scene linking Motorcycle's files `names`, with its own calib.txt."""
    scene = tmp_path / 'Motorcycle'
    scene.mkdir()
    for name in names:
        (scene / name).symlink_to(data_dir / MIDDEVAL3 / 'trainingQ/Motorcycle' / name)
    if calib is not None:
        (scene / 'calib.txt').write_text(calib)
    return scene


def test_pfm_big_endian_and_damaged(tmp_path, data_dir, frames):
    """A positive scale means big-endian values; a truncated or colour PFM is refused."""
    real = (data_dir / MIDDEVAL3 / 'trainingQ/Motorcycle/disp0GT.pfm').read_bytes()
    header = b'Pf\n741 497\n-0.003922\n'
    assert real.startswith(header)
    values = np.frombuffer(real[len(header):], '<f4')
    scene = scene_copy(tmp_path, data_dir, ['im0.png', 'im1.png'], 'ndisp=70\n')
    big_endian = b'Pf\n741 497\n0.003922\n' + values.astype('>f4').tobytes()
    (scene / 'disp0GT.pfm').write_bytes(big_endian)
    gt = load_frame(scene, 'Motorcycle').gt
    moto = frames[str(MIDDEVAL3 / 'trainingQ/Motorcycle')]
    assert np.array_equal(gt, moto.gt, equal_nan=True)
    for bad, why in ((real[:-4], '368276 values for a 741x497'),
                     (b'PF' + real[2:], 'one-channel')):
        (scene / 'disp0GT.pfm').write_bytes(bad)
        with pytest.raises(ValueError, match=why):
            load_frame(scene, 'Motorcycle')


def test_middeval3_calib(tmp_path, data_dir):
    scene = scene_copy(tmp_path, data_dir, ['im0.png', 'im1.png', 'disp0GT.pfm'],
                       'width=741\nndisp=100\nvmin=7\n')
    f = load_frame(scene, 'Motorcycle')
    assert f.max_disp == 112 and 'no mask0nocc.png' in f.note and 'ndisp' not in f.note
    (scene / 'calib.txt').write_text('ndisp=many\n')
    with pytest.raises(ValueError, match='calib.txt: ndisp=many is not an integer'):
        load_frame(scene, 'Motorcycle')
    (scene / 'calib.txt').write_text('cam0=[999 0 294; 0 999 252]\n'
                                     'cam1=[999 0 326; 0 999 252; 0 0 1]\nbaseline=193.001\n')
    with pytest.raises(ValueError, match='cam0, cam1 or baseline is not a 3x3 matrix'):
        load_frame(scene, 'Motorcycle')
    (scene / 'calib.txt').write_text('cam0=[999 0 294; 0 999 252; 0 0 1]\n'
                                     'cam1=[999 0 326; 0 999 252; 0 0 1]\nbaseline=193.001\n')
    f = load_frame(scene, 'Motorcycle')
    assert (f.focal_px, f.principal_px, f.doffs_px) == (999, (294, 252), 32)
    assert f.baseline_m == 0.193001


def test_kitti2015_occluded_ground_truth_only(kitti_occ_only, data_dir):
    """Without disp_noc_0 a frame is scored on disp_occ_0 and says so; without GT, not listed."""
    assert list_frames(kitti_occ_only) == ['kitti2015/000001_10']
    occ = load_frame(kitti_occ_only, 'kitti2015/000001_10')
    raw = np.array(Image.open(data_dir / 'kitti2015/training/disp_occ_0/000001_10.png'))
    assert (occ.valid == (raw > 0)).all() and (occ.gt[raw > 0] == raw[raw > 0] / 256).all()
    assert occ.note == ('scored on disp_occ_0 (occluded pixels included): '
                        'no disp_noc_0/000001_10.png')
    noc = load_frame(data_dir, 'kitti2015/000001_10')  # the shared folder has both
    assert noc.note is None and (noc.valid <= occ.valid).all()
    assert occ.valid.sum() > noc.valid.sum()  # 107175 vs 106133 pixels
