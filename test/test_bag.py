"""
gcp-stereo-bag on real data: make -> run round trips, and play into the node.

The other bag tests: test_bag_refusals.py, test_bag_play.py, test_bag_raw.py.
"""
import contextlib
import io
import os

from bag_helpers import cli, Listener, PARAMS, read_bag
import cv2
from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.evaluation.metrics import error_rates
from gcp_stereo_ros.evaluation.viz import disparity_picture
from gcp_stereo_ros.ros import messages
from gcp_stereo_ros.ros.camera import stereo_model
from gcp_stereo_ros.ros.graph import start_node, stop
from gcp_stereo_ros.ros.params import config_from_params
from gcp_stereo_ros.ros.rosimage import image_to_array
from gcp_stereo_ros.stereo.pipeline import StereoPipeline
from gcp_stereo_ros.tools import bag
from gcp_stereo_ros.tools.bag import make as bag_make, run as bag_run
from gcp_stereo_ros.tools.bag.files import COMPRESSED, stamped_header
import numpy as np
import pytest


@pytest.fixture(scope='module')
def expected():
    """(dataset, frame name) -> (Frame, StereoResult of the pipeline the node would build)."""
    pipeline = StereoPipeline(config_from_params(PARAMS))
    cache = {}

    def get(dataset, name):
        if name not in cache:
            frame = load_frame(dataset, name)
            cache[name] = frame, pipeline(frame.left, frame.right)
        return cache[name]
    return get


def test_make_writes_the_node_inputs_and_ground_truth(tmp_path, data_dir):
    names = ['kitti2012/000070_10', 'middlebury_v2/venus']
    out = tmp_path / 'in_bag'
    assert bag.main(['make', '--dataset', str(data_dir), '--frames', *names,
                     '--storage', 'sqlite3', '--out', str(out), '--rate', '20',
                     '--namespace', 'stereo']) == 0
    msgs, conns = read_bag(out)
    assert set(conns) == {
        f'/stereo/{t}' for t in ('left/image_rect', 'right/image_rect', 'left/camera_info',
                                 'right/camera_info', 'gt/disparity', 'gt/valid', 'gt/frame_name')}
    for topic in ('/stereo/left/image_rect', '/stereo/right/camera_info'):
        qos, = conns[topic].ext.offered_qos_profiles
        assert (qos.reliability.name, qos.durability.name, qos.history.name, qos.depth) == \
            ('BEST_EFFORT', 'VOLATILE', 'KEEP_LAST', 5)
    stamps = [messages.stamp_ns(m.header) for _, m in msgs['/stereo/left/image_rect']]
    assert np.diff(stamps).tolist() == [50_000_000]
    assert [m.data for _, m in msgs['/stereo/gt/frame_name']] == names
    for i, name in enumerate(names):
        frame = load_frame(data_dir, name)
        for side in ('left', 'right'):
            timestamp, image = msgs[f'/stereo/{side}/image_rect'][i]
            assert timestamp == messages.stamp_ns(image.header) == stamps[i]
            assert image.header.frame_id == f'{side}_camera'
            assert image.encoding == ('rgb8' if frame.left.ndim == 3 else 'mono8')
            np.testing.assert_array_equal(image_to_array(image), getattr(frame, side))
        gt = image_to_array(msgs['/stereo/gt/disparity'][i][1])
        valid = image_to_array(msgs['/stereo/gt/valid'][i][1]) == 255
        np.testing.assert_array_equal(valid, frame.valid & np.isfinite(frame.gt))
        np.testing.assert_array_equal(gt[valid], frame.gt[valid])
        assert (gt[~np.isfinite(frame.gt)] == 0).all()
        info = msgs['/stereo/right/camera_info'][i][1]
        assert (info.width, info.height) == frame.left.shape[1::-1]
    kitti = load_frame(data_dir, names[0])
    assert 700 < kitti.focal_px < 750 and 0.5 < kitti.baseline_m < 0.6  # the calibration was read
    p_left, p_right = (msgs[f'/stereo/{s}/camera_info'][0][1].p for s in ('left', 'right'))
    assert p_left[0] == p_right[0] == pytest.approx(kitti.focal_px) and p_left[3] == 0
    assert p_right[3] == pytest.approx(-kitti.focal_px * kitti.baseline_m)
    assert not msgs['/stereo/right/camera_info'][1][1].p.any()  # Middlebury v2: no calibration


def test_motorcycle_camera_info_gives_depth(data_dir):
    """
    The Motorcycle pairs' camera_info carries their calibration, principal points included.

    Depth of the ground-truth disparities through it: 10th/50th/90th percentile 2.27 / 2.75 /
    4.44 m for scikit-image's pair (documented calibration), 2.17 / 2.52 / 4.06 m for
    MiddEval3's quarter-size one (calib.txt); without the principal points' offset (doffs,
    31 and 33 px) the medians would be 4.96 and 4.42 m.
    """
    for source, name in (('motorcycle', 'motorcycle'),
                         (data_dir, 'middeval3/MiddEval3/trainingQ/Motorcycle')):
        frame = load_frame(source, name)
        infos = [bag_make.camera_info(stamped_header(0, f'{side}_camera'), frame, side)
                 for side in ('left', 'right')]
        model = stereo_model(*infos, frame.left.shape, frame.max_disp)
        assert model.cx_offset == pytest.approx(-frame.doffs_px) and frame.doffs_px > 30
        depth = model.depth(np.where(frame.valid, frame.gt, np.nan).astype(np.float32))
        assert 2.4 < np.nanmedian(depth) < 2.9


@pytest.fixture(scope='module')
def round_trip(tmp_path_factory, params_file):
    """
    Map (storage, dataset, frame names) -> (input bag, output bag, stdout of run).

    Make, then run.
    """
    cache = {}

    def get(storage, dataset, names):
        key = storage, dataset, tuple(names)
        if key not in cache:
            folder = tmp_path_factory.mktemp(storage)
            bag_in, bag_out = folder / 'in', folder / 'out'
            assert bag.main(['make', '--dataset', dataset, '--frames', *names,
                             '--storage', storage, '--out', str(bag_in)]) == 0
            stdout = io.StringIO()
            with contextlib.redirect_stdout(stdout):
                assert bag.main(['run', '--in', str(bag_in), '--out', str(bag_out),
                                 '--params', str(params_file), '--png', str(folder / 'png'),
                                 '--storage', storage]) == 0
            cache[key] = bag_in, bag_out, stdout.getvalue()
        return cache[key]
    return get


@pytest.mark.parametrize('storage, dataset, names', [
    ('sqlite3', 'motorcycle', ['motorcycle']),
    ('mcap', 'motorcycle', ['motorcycle']),
    ('mcap', 'shared', ['middlebury_v2/cones']),
])
def test_run_gives_the_node_outputs_and_scores(data_dir, round_trip, expected,
                                               storage, dataset, names):
    dataset = str(data_dir) if dataset == 'shared' else dataset
    bag_in, bag_out, stdout = round_trip(storage, dataset, names)
    lines = stdout.splitlines()
    inputs, _ = read_bag(bag_in)
    outputs, conns = read_bag(bag_out)
    assert set(inputs) < set(outputs) and {'/disparity', '/gcp_mask', '/confidence'} < set(outputs)
    assert conns['/left/image_rect'].ext.offered_qos_profiles[0].reliability.name == 'BEST_EFFORT'
    rows = {line.split()[-1]: line.split()[:-1] for line in lines}
    for i, name in enumerate(names):
        frame, result = expected(dataset, name)
        left = inputs['/left/image_rect'][i][1]
        disp_msg, gcp_msg, conf_msg = (
            outputs[t][i][1] for t in ('/disparity', '/gcp_mask', '/confidence'))
        for msg in (disp_msg, gcp_msg, conf_msg):
            assert messages.stamp_ns(msg.header) == messages.stamp_ns(left.header)
            assert msg.header.frame_id == left.header.frame_id == 'left_camera'
        low = np.float32(frame.doffs_px)  # d = 0 in the message: d - (cx_left - cx_right)
        want = np.where(np.isnan(result.disparity), low - 1, result.disparity + low)
        np.testing.assert_array_equal(image_to_array(disp_msg.image), want)
        assert disp_msg.min_disparity == low and disp_msg.f == np.float32(frame.focal_px or 0)
        assert disp_msg.max_disparity == np.float32(PARAMS['max_disparity'] - 1 + low)
        np.testing.assert_array_equal(image_to_array(gcp_msg), result.gcp.astype(np.uint8) * 255)
        np.testing.assert_array_equal(image_to_array(conf_msg), result.cof_c)
        assert 0 < result.gcp.mean() < 1  # neither empty nor full: the comparison can tell
        rates = error_rates(result.disparity, frame.gt, frame.valid)
        assert rows[name] == [f'{rates[k]:.2f}' for k in bag_run.RATE_KEYS]
        stem = name.replace('/', '_')
        assert {p.name for p in (bag_out.parent / 'png').iterdir()} == {
            f'{stem}_disparity.png', f'{stem}_gcp_mask.png'}
        picture = cv2.imread(str(bag_out.parent / 'png' / f'{stem}_disparity.png'))
        np.testing.assert_array_equal(  # the map with its colour bar under it
            picture, disparity_picture(result.disparity, PARAMS['max_disparity']))
        assert picture.shape[0] > result.disparity.shape[0]
    assert 'mean' in rows
    for topic in inputs:  # the input is copied unchanged
        assert [t for t, _ in outputs[topic]] == [t for t, _ in inputs[topic]]
    # no staging left
    assert sorted(p.name for p in bag_out.parent.iterdir()) == ['in', 'out', 'png']


def test_play_into_the_node_gives_what_run_gives(data_dir, params_file, round_trip, ros):
    from rcl_interfaces.msg import Log
    from sensor_msgs.msg import Image
    from stereo_msgs.msg import DisparityImage
    bag_in, bag_out, _ = round_trip('mcap', str(data_dir), ['middlebury_v2/cones'])
    offline, _ = read_bag(bag_out)
    listener = Listener(ros, 'test_bag_node_listener',
                        {'/disparity': DisparityImage, '/gcp_mask': Image, '/rosout': Log})
    node = start_node(os.environ, params_file=params_file)
    try:
        # into the running node, as a user would
        listener.wait(lambda: any(m.msg.startswith('ready') for _, m in listener.got['/rosout']),
                      'the node', 60)
        proc = cli('play', '--in', bag_in, '--wait-subscribers', 10)
        assert proc.returncode == 0 and 'no subscriber' not in proc.stderr, proc.stderr
        listener.wait(lambda: listener.got['/disparity'] and listener.got['/gcp_mask'],
                      'the outputs', timeout=30)
    finally:
        listener.close()
        node_exit = stop(node)
    assert node_exit == 0
    scalars = ('f', 't', 'min_disparity', 'max_disparity', 'delta_d')
    roi = ('x_offset', 'y_offset', 'width', 'height')
    for (_, live), (_, off) in zip(listener.got['/disparity'], offline['/disparity'], strict=True):
        assert messages.stamp_ns(live.header) == messages.stamp_ns(off.header)
        assert live.header.frame_id == off.header.frame_id
        np.testing.assert_array_equal(image_to_array(live.image), image_to_array(off.image))
        assert [getattr(live, k) for k in scalars] == [getattr(off, k) for k in scalars]
        assert ([getattr(live.valid_window, k) for k in roi]
                == [getattr(off.valid_window, k) for k in roi])
    for (_, live), (_, off) in zip(listener.got['/gcp_mask'], offline['/gcp_mask'], strict=True):
        np.testing.assert_array_equal(image_to_array(live), image_to_array(off))


def test_compressed_png_bag_gives_exactly_the_raw_bags_outputs(tmp_path, params_file, round_trip,
                                                               capsys):
    _, raw_out, _ = round_trip('mcap', 'motorcycle', ['motorcycle'])
    bag_in, bag_out = tmp_path / 'png_in', tmp_path / 'png_out'
    assert bag.main(['make', '--dataset', 'motorcycle', '--compressed', 'png',
                     '--out', str(bag_in)]) == 0
    msgs, conns = read_bag(bag_in)
    left, = (m for _, m in msgs['/left/image_rect/compressed'])
    assert conns['/left/image_rect/compressed'].msgtype == COMPRESSED
    assert left.format == 'rgb8; png compressed bgr8'  # as image_transport writes it
    assert bag.main(['run', '--in', str(bag_in), '--out', str(bag_out),
                     '--params', str(params_file)]) == 0
    assert '/left/image_rect/compressed + /right/image_rect/compressed' in capsys.readouterr().out
    got, _ = read_bag(bag_out)
    want, _ = read_bag(raw_out)
    for topic in ('/disparity', '/gcp_mask', '/confidence'):
        (_, a), = got[topic]
        (_, b), = want[topic]
        np.testing.assert_array_equal(image_to_array(getattr(a, 'image', a)),
                                      image_to_array(getattr(b, 'image', b)))
