"""Shared test set-up: where the real data lives, and an isolated ROS 2 graph per process."""
import os
from pathlib import Path
from types import SimpleNamespace

from gcp_stereo_ros.ros.graph import join_private_graph
import numpy as np
import pytest

# Every test process gets its own DDS domain on loopback only, so parallel runs never
# cross-talk; the shipped Fast DDS profile lets large images through shared memory.
join_private_graph(1 + os.getpid() % 100)

# GCP_STEREO_DATA: elsewhere (a GPU machine, where the frames travel inside the checkout).
DATA = Path(os.environ.get('GCP_STEREO_DATA',
                           Path(__file__).resolve().parents[2] / 'shared' / 'data')).resolve()


@pytest.fixture(scope='module')
def ros():
    """rclpy, initialized for the tests of one module and shut down after them."""
    import rclpy
    rclpy.init()
    yield rclpy
    rclpy.shutdown()


@pytest.fixture(scope='module')
def net():
    """Return the shipped CNN, loaded once per test module (torch only where it is used)."""
    from gcp_stereo_ros.stereo.cnn.network import load_net
    return load_net()


@pytest.fixture(scope='module')
def tsukuba(data_dir):
    """Return Middlebury v2 tsukuba, a training frame of the shipped CNN."""
    from gcp_stereo_ros.evaluation.datasets import load_frame
    return load_frame(data_dir, 'middlebury_v2/tsukuba')


@pytest.fixture(scope='session')
def data_dir():
    """`../shared/data` beside the checkout; CI always has it, so its absence fails loudly."""
    assert DATA.is_dir(), f'real test data expected at {DATA}'
    return DATA


@pytest.fixture(scope='session')
def distorted_pair():
    """
    Motorcycle at a third of its size, rectified, and the raw pair a real rig would record.

    The rectified cameras have focal length F px and baseline T m (principal point at the
    centre); each raw camera has its own K, plumb_bob D (barrel distortion) and a 1 degree
    rotation R. Raw pixels are sampled from the rectified images through the inverse map
    (bicubic), so rectifying the raw pair with K, D, R, P must give the rectified pair back.
    `info[side]` holds the CameraInfo fields of the raw cameras.
    """
    import cv2
    from skimage import data
    left, right, _ = data.stereo_motorcycle()
    rect = {s: cv2.resize(im, (247, 167), interpolation=cv2.INTER_AREA)
            for s, im in (('left', left), ('right', right))}
    h, w = rect['left'].shape[:2]
    f, baseline = 330.0, 0.2
    grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float32),
                                np.arange(h, dtype=np.float32)), -1).reshape(-1, 1, 2)
    raw, info = {}, {}
    for side, axis, angle, d in (('left', [0.3, 1, 0.1], 1.0, [-0.28, 0.09, 0.001, -5e-4, 0]),
                                 ('right', [0.2, 1, -0.1], -1.0, [-0.25, 0.07, -0.001, 8e-4, 0])):
        p = np.array([[f, 0, w / 2, -f * baseline if side == 'right' else 0.0],
                      [0, f, h / 2, 0], [0, 0, 1, 0]])
        k = np.array([[1.05 * f, 0, w / 2 + 3], [0, 1.05 * f, h / 2 - 2], [0, 0, 1]])
        r = cv2.Rodrigues(np.array(axis) * np.radians(angle))[0]
        at = cv2.undistortPoints(grid, k, np.array(d), R=r, P=p).reshape(h, w, 2)
        raw[side] = cv2.remap(rect[side], at[..., 0], at[..., 1], cv2.INTER_CUBIC)
        info[side] = {'width': w, 'height': h, 'distortion_model': 'plumb_bob',
                      'd': np.array(d, float), 'k': k.ravel(), 'r': r.ravel(), 'p': p.ravel()}
    return SimpleNamespace(rect=rect, raw=raw, info=info, f=f, baseline=baseline)


@pytest.fixture(scope='session')
def kitti70(data_dir):
    """Return the gray pair (float32) of KITTI 2012 000070_10, the unseen test frame."""
    from gcp_stereo_ros.evaluation.datasets import load_frame
    from gcp_stereo_ros.stereo.images import gray_pair
    frame = load_frame(data_dir, 'kitti2012/000070_10')
    return gray_pair(frame.left, frame.right)


@pytest.fixture
def kitti_occ_only(tmp_path, data_dir):
    """
    Build a KITTI 2015 folder whose frame 000001_10 has disp_occ_0 but no disp_noc_0.

    Frame 000002_10 has images and no ground truth at all. Files link to the shared data.
    """
    shared = data_dir / 'kitti2015' / 'training'
    training = tmp_path / 'kitti2015' / 'training'
    for sub, stems in (('image_2', ('000001_10', '000002_10')),
                       ('image_3', ('000001_10', '000002_10')), ('disp_occ_0', ('000001_10',))):
        (training / sub).mkdir(parents=True)
        for stem in stems:
            (training / sub / f'{stem}.png').symlink_to(shared / sub / f'{stem}.png')
    return tmp_path


@pytest.fixture(scope='module')
def pair():
    """Motorcycle at a third of its size: real texture, quick to match."""
    import cv2
    from skimage import data
    left, right, _ = data.stereo_motorcycle()
    return tuple(cv2.resize(im, (247, 167), interpolation=cv2.INTER_AREA) for im in (left, right))


@pytest.fixture
def harness(ros, request):
    """Yield a `Harness`: the node (`max_disparity` 32, then the test's parameters), its peer."""
    from ros_helpers import Harness, MAX_DISP
    overrides = {'max_disparity': MAX_DISP, **getattr(request, 'param', {})}
    h = Harness(overrides)
    h.overrides = overrides
    yield h
    h.close()


@pytest.fixture(scope='module')
def params_file(tmp_path_factory):
    """Return a parameters file of the bag tests' node parameters (`bag_helpers.PARAMS`)."""
    import yaml
    from bag_helpers import PARAMS
    path = tmp_path_factory.mktemp('params') / 'gcp_stereo.yaml'
    path.write_text(yaml.safe_dump({'gcp_stereo_node': {'ros__parameters': PARAMS}}))
    return path
