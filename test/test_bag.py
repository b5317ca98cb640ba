"""
gcp-stereo-bag on real data.

make -> run round trips, bad input bags, play into live subscribers.
"""
import contextlib
import io
import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import threading
import time

import cv2
from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.evaluation.metrics import error_rates
from gcp_stereo_ros.evaluation.viz import disparity_picture
from gcp_stereo_ros.ros.camera import stereo_model
from gcp_stereo_ros.ros.graph import start_node, stop
from gcp_stereo_ros.ros.params import config_from_params
from gcp_stereo_ros.ros.rosimage import array_to_image_fields, image_to_array
from gcp_stereo_ros.stereo.pipeline import StereoPipeline
from gcp_stereo_ros.tools import bag
from gcp_stereo_ros.tools.bag import make as bag_make, run as bag_run
from gcp_stereo_ros.tools.bag.files import (COMPRESSED, IMAGE, INFO, PROG, stamped_header,
                                            STRING, TYPES)
import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores
import yaml

REPO = Path(__file__).resolve().parents[1]
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)  # read back independently of the module under test
PARAMS = {'max_disparity': 64}  # the node's defaults otherwise (census, GCPs, shipped weights)


@pytest.fixture(scope='module')
def params_file(tmp_path_factory):
    path = tmp_path_factory.mktemp('params') / 'gcp_stereo.yaml'
    path.write_text(yaml.safe_dump({'gcp_stereo_node': {'ros__parameters': PARAMS}}))
    return path


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


def read_bag(path):
    """({topic: [(bag timestamp, message)]}, {topic: connection}) of a whole bag."""
    msgs = {}
    with Reader(path) as reader:
        conns = {c.topic: c for c in reader.connections}
        for conn, timestamp, raw in reader.messages():
            msgs.setdefault(conn.topic, []).append(
                (timestamp, TYPESTORE.deserialize_cdr(raw, conn.msgtype)))
    return msgs, conns


def stamp_of(msg):
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def cli(*args):
    """
    Run `python -m gcp_stereo_ros.tools.bag ARGS` as a user runs it.

    It runs in the test's ROS environment.
    """
    return subprocess.run(
        [sys.executable, '-m', 'gcp_stereo_ros.tools.bag', *map(str, args)],
        cwd=REPO, env=os.environ, capture_output=True, text=True, timeout=120)


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
    stamps = [stamp_of(m) for _, m in msgs['/stereo/left/image_rect']]
    assert np.diff(stamps).tolist() == [50_000_000]
    assert [m.data for _, m in msgs['/stereo/gt/frame_name']] == names
    for i, name in enumerate(names):
        frame = load_frame(data_dir, name)
        for side in ('left', 'right'):
            timestamp, image = msgs[f'/stereo/{side}/image_rect'][i]
            assert timestamp == stamp_of(image) == stamps[i]
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
            assert stamp_of(msg) == stamp_of(left)
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


def write_bag(path, topics, storage='sqlite3'):
    """Write a bag of {topic: (msgtype, [(timestamp, message)])} with rosbags directly."""
    with Writer(path, version=9, storage_plugin=StoragePlugin[storage.upper()]) as writer:
        for topic, (msgtype, msgs) in topics.items():
            conn = writer.add_connection(topic, msgtype, typestore=TYPESTORE)
            for timestamp, msg in msgs:
                writer.write(conn, timestamp, TYPESTORE.serialize_cdr(msg, msgtype))


def string_msg(text):
    return TYPESTORE.types[STRING](data=text)


def image_msg(stamp, encoding, size=(80, 60)):
    w, h = size
    header = stamped_header(stamp, 'left_camera')
    return TYPESTORE.types[IMAGE](header=header, height=h, width=w, encoding=encoding,
                                  is_bigendian=0, step=w * 3,
                                  data=np.zeros(w * h * 3, np.uint8))


def bad_bags(tmp_path):
    """{case: path} of inputs `run` must refuse."""
    bags = {}
    for storage in ('sqlite3', 'mcap'):
        good = tmp_path / f'good_{storage}'
        assert bag.main(['make', '--dataset', 'motorcycle', '--storage', storage,
                         '--out', str(good)]) == 0
        cut = bags[f'truncated {storage}'] = tmp_path / f'truncated_{storage}'
        shutil.copytree(good, cut)
        data, = (p for p in cut.iterdir() if p.suffix in ('.db3', '.mcap'))
        data.write_bytes(data.read_bytes()[:data.stat().st_size // 2])
    bags['text file'] = tmp_path / 'notes.txt'
    bags['text file'].write_text('not a bag\n')
    bags['text file named .db3'] = tmp_path / 'notes.db3'
    bags['text file named .db3'].write_text('not a bag\n')
    bags['no image topics'] = tmp_path / 'chatter'
    write_bag(bags['no image topics'], {'/chatter': (STRING, [(1, string_msg('hello'))])})
    bags['wrong image type'] = tmp_path / 'strings'
    write_bag(bags['wrong image type'], {
        '/left/image_rect': (STRING, [(1, string_msg('left'))]),
        '/right/image_rect': (STRING, [(1, string_msg('right'))])})
    bags['only bad pairs'] = tmp_path / 'only_bad'
    write_bag(bags['only bad pairs'], {
        f'/{side}/image_rect': (
            IMAGE, [(1, image_msg(1, 'yuv422')), (2, image_msg(2, 'yuv422'))])
        for side in ('left', 'right')})
    return bags


REASONS = {
    'truncated sqlite3': 'malformed', 'truncated mcap': 'not a readable rosbag2',
    'text file': 'not a readable rosbag2', 'text file named .db3': 'not a database',
    'no image topics': 'no stereo pair of image topics (topics: /chatter (String))',
    'wrong image type': 'no stereo pair of image topics (topics: /left/image_rect (String), '
                        '/right/image_rect (String))',
    'only bad pairs': 'none of its 2 pairs could be processed',
}


def test_bad_input_bags_are_refused_without_output(tmp_path, params_file, capsys):
    bags = bad_bags(tmp_path)
    capsys.readouterr()
    for case, path in bags.items():
        out = tmp_path / f'out_{path.name}'
        assert bag.main(['run', '--in', str(path), '--out', str(out),
                         '--params', str(params_file)]) != 0, case
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert err.startswith('gcp-stereo-bag: error: ') and REASONS[case] in err, (case, err)
        assert err.endswith(f'{out} not written'), err
        assert not out.exists(), case
    assert [p.name for p in tmp_path.iterdir() if 'partial' in p.name] == []
    # the real command line: exit status 1, one line on stderr, no traceback
    proc = cli('run', '--in', bags['truncated mcap'], '--out', tmp_path / 'cli_out')
    assert proc.returncode == 1 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert 'Traceback' not in proc.stderr and not (tmp_path / 'cli_out').exists()


def crop_msg(frame, side, stamp, encoding='rgb8', rows=120):
    image = getattr(frame, side)[200:200 + rows, 300:460]
    fields = array_to_image_fields(image, 'rgb8')
    return TYPESTORE.types[IMAGE](header=stamped_header(stamp, f'{side}_camera'),
                                  **{**fields, 'encoding': encoding})


def test_run_skips_a_bad_pair_as_the_node_does(tmp_path, params_file, capsys):
    frame = load_frame('motorcycle', 'motorcycle')
    path = tmp_path / 'in'
    write_bag(path, {f'/{side}/image_rect': (IMAGE, [
        (1, crop_msg(frame, side, 1)),
        (2, crop_msg(frame, side, 2, 'yuv422' if side == 'left' else 'rgb8')),
        (3, crop_msg(frame, side, 3, rows=120 if side == 'left' else 100)),
        (4, crop_msg(frame, side, 4))]) for side in ('left', 'right')})
    assert bag.main(['run', '--in', str(path), '--out', str(tmp_path / 'out'),
                     '--params', str(params_file)]) == 0
    out = capsys.readouterr()
    assert [line for line in out.err.splitlines() if line.startswith(PROG)] == [
        'gcp-stereo-bag: skipping pair at stamp 2 ns: /left/image_rect: unsupported '
        "encoding 'yuv422'; expected one of mono8, mono16, 32FC1, rgb8, bgr8, rgba8, bgra8",
        'gcp-stereo-bag: skipping pair at stamp 3 ns: left image is 160x120 but right '
        'image is 160x100 (width x height); a rectified pair has one size']
    assert ' processed (confidence, disparity, gcp_mask written), 2 skipped;' in out.out
    outputs, _ = read_bag(tmp_path / 'out')
    assert [stamp_of(m) for _, m in outputs['/disparity']] == [1, 4]
    too_high = tmp_path / 'theta.yaml'  # the shipped weights' confidence is at most 0.961
    too_high.write_text(yaml.safe_dump(
        {'/**': {'ros__parameters': {**PARAMS, 'census.theta': 0.97}}}))
    assert bag.main(['run', '--in', str(path), '--out', str(tmp_path / 'out'), '--force',
                     '--params', str(too_high)]) == 0
    assert ('gcp-stereo-bag: warning: theta 0.97 selects no GCP: the CNN confidence is at most'
            in capsys.readouterr().err)


def test_run_pairs_free_running_cameras_by_the_closest_stamps(tmp_path, capsys):
    """approximate_sync with tolerance 0: the right camera 7 ms late, left image 2 lost."""
    frame, ms = load_frame('motorcycle', 'motorcycle'), 1_000_000
    stamps = {'left': [0, 66 * ms, 99 * ms], 'right': [7 * ms, 40 * ms, 73 * ms, 106 * ms]}
    write_bag(tmp_path / 'in', {f'/{side}/image_rect': (IMAGE, [
        (t, crop_msg(frame, side, t)) for t in stamps[side]]) for side in stamps})
    params = tmp_path / 'approximate.yaml'
    params.write_text(yaml.safe_dump(
        {'/**': {'ros__parameters': {**PARAMS, 'approximate_sync': True}}}))
    assert bag.main(['run', '--in', str(tmp_path / 'in'), '--out', str(tmp_path / 'out'),
                     '--params', str(params)]) == 0
    outputs, _ = read_bag(tmp_path / 'out')
    # the first frame goes: the frame period is known from a side's second image on
    assert [stamp_of(m) for _, m in outputs['/disparity']] == stamps['left'][1:]
    assert 'images without a twin skipped: left 1, right 2' in capsys.readouterr().out
    one = tmp_path / 'one'  # a recording of one frame: the closest stamps
    write_bag(one, {f'/{side}/image_rect': (IMAGE, [(stamps[side][0], crop_msg(
        frame, side, stamps[side][0]))]) for side in stamps})
    assert bag.main(['run', '--in', str(one), '--out', str(tmp_path / 'one_out'),
                     '--params', str(params)]) == 0
    assert [stamp_of(m) for _, m in read_bag(tmp_path / 'one_out')[0]['/disparity']] == [0]


def slow_bag(path, pairs):
    """Write a bag of `pairs` Motorcycle frames: seconds of work for `run`."""
    frame = load_frame('motorcycle', 'motorcycle')
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {name: writer.add_connection(f'/{name}', msgtype, typestore=TYPESTORE)
                 for name, (msgtype, _) in bag_make.input_topics().items()}
        for i in range(pairs):
            stamp = (i + 1) * 100_000_000
            for name, msg in bag_make.frame_messages(frame, stamp).items():
                if name in conns:
                    writer.write(conns[name], stamp,
                                 TYPESTORE.serialize_cdr(msg, conns[name].msgtype))


def test_staging_is_removed_on_sigterm_and_after_sigkill(tmp_path):
    slow_bag(tmp_path / 'in', 20)
    out = tmp_path / 'out'
    for sig in (signal.SIGTERM, signal.SIGKILL):
        proc = subprocess.Popen([sys.executable, '-m', 'gcp_stereo_ros.tools.bag', 'run',
                                 '--in', str(tmp_path / 'in'), '--out', str(out)],
                                cwd=REPO, env=os.environ, stderr=subprocess.PIPE, text=True)
        staging = tmp_path / f'.out.partial-{proc.pid}'
        end = time.monotonic() + 60
        while not staging.exists():
            assert time.monotonic() < end and proc.poll() is None, 'no staging folder'
            time.sleep(0.05)
        time.sleep(1.0)  # in the middle of the run
        proc.send_signal(sig)
        err = proc.communicate(timeout=30)[1]
        if sig == signal.SIGTERM:
            assert proc.returncode == 128 + signal.SIGTERM, err
            assert err.strip().splitlines()[-1] == (
                f'gcp-stereo-bag: terminated; {out} not written')
            assert not staging.exists()
        else:
            assert staging.exists()  # nothing runs on SIGKILL ...
    assert not out.exists()
    assert bag.main(['make', '--dataset', 'motorcycle', '--out', str(out)]) == 0
    assert not staging.exists()  # ... the next run on the same output removes it
    assert sorted(p.name for p in tmp_path.iterdir()) == ['in', 'out']


def test_play_warns_of_messages_larger_than_the_shared_memory_segment(tmp_path):
    gray = load_frame('motorcycle', 'motorcycle').left.mean(axis=2).astype(np.uint8)
    big = np.tile(gray, (13, 9))[:6000, :6000]  # 36 MB as mono8
    fields = array_to_image_fields(big, 'mono8')
    msg = TYPESTORE.types[IMAGE](header=stamped_header(1, 'left_camera'), **fields)
    write_bag(tmp_path / 'big', {'/left/image_rect': (IMAGE, [(1, msg)])})
    proc = cli('play', '--in', tmp_path / 'big', '--wait-subscribers', 0)
    assert proc.returncode == 0, proc.stderr
    assert ('gcp-stereo-bag play: warning: /left/image_rect has messages of 34.3 MiB, more than '
            'the 32 MiB Fast DDS shared-memory segment') in proc.stderr


def test_existing_output_needs_force(tmp_path, capsys):
    out = tmp_path / 'bag'
    out.mkdir()
    (out / 'keep').write_text('mine')
    make = ['make', '--dataset', 'motorcycle', '--out', str(out)]
    assert bag.main(make) == 1
    assert 'exists; pass --force' in capsys.readouterr().err
    assert (out / 'keep').read_text() == 'mine'
    assert bag.main(make + ['--force']) == 0
    assert not (out / 'keep').exists()
    assert read_bag(out)[0]['/gt/frame_name'][0][1].data == 'motorcycle'


@pytest.mark.parametrize('values, reason', [
    ({'max_disparity': 2000}, 'max_disparity must be in [1, 1024], got 2000'),
    ({'census.window': 8}, 'census.window must be in [3, 11] in steps of 2 from 3, got 8'),
    ({'sad.P1': 30.0}, 'sad: P2 (0.5) must be >= P1 (30.0)'),
])
def test_run_refuses_bad_parameters_naming_the_file(tmp_path, capsys, values, reason):
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({'/**': {'ros__parameters': values}}))
    out = tmp_path / 'out'
    assert bag.main(['run', '--in', str(tmp_path / 'no_bag'), '--out', str(out),
                     '--params', str(params)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f'gcp-stereo-bag: error: {params}: {reason}' + (
        ': a disparity jump may not cost less than a 1 px step' if 'P2' in reason else '') + (
        f'; {out} not written')
    assert not out.exists()


# ---- play -------------------------------------------------------------------------------
class Listener:
    """A node recording (arrival time, message) per topic, spun in a thread."""

    def __init__(self, rclpy, name, topics):
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        self.node = rclpy.create_node(name)
        self.got = {topic: [] for topic in topics}
        # matches any publisher
        best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
        # also what came before
        rosout = QoSProfile(depth=1000, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        for topic, cls in topics.items():
            self.node.create_subscription(
                cls, topic, lambda m, t=topic: self.got[t].append((time.monotonic(), m)),
                rosout if topic == '/rosout' else best_effort)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def wait(self, condition, what, timeout):
        end = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < end, f'timed out waiting for {what}: got {self.counts()}'
            time.sleep(0.02)

    def counts(self):
        return {topic: len(msgs) for topic, msgs in self.got.items()}

    def close(self):
        self.executor.shutdown()
        self.thread.join()
        self.node.destroy_node()


def test_play_publishes_every_image_in_order(tmp_path, data_dir, ros):
    from sensor_msgs.msg import CameraInfo, Image
    # rgb8, mono8, 1 MB
    names = ['middlebury_v2/cones', 'kitti2012/000070_10', 'middlebury2006/halfsize/Cloth3']
    bag_path = tmp_path / 'bag'
    assert bag.main(['make', '--dataset', str(data_dir), '--frames', *names,
                     '--out', str(bag_path)]) == 0
    recorded, _ = read_bag(bag_path)
    listener = Listener(ros, 'test_bag_play_listener',
                        {'/left/image_rect': Image, '/right/image_rect': Image,
                         '/right/camera_info': CameraInfo})
    try:
        proc = cli('play', '--in', bag_path, '--rate', 0.5, '--wait-subscribers', 20)
        assert proc.returncode == 0 and 'no subscriber' not in proc.stderr, proc.stderr
        listener.wait(lambda: min(listener.counts().values()) == len(names), 'every message',
                      timeout=10)
    finally:
        listener.close()
    for topic, got in listener.got.items():
        want = [m for _, m in recorded[topic]]
        assert [stamp_of(m) for _, m in got] == [stamp_of(m) for m in want], topic
        assert [m.header.frame_id for _, m in got] == [m.header.frame_id for m in want]
        if topic.endswith('image_rect'):
            for (_, m), w in zip(got, want):
                np.testing.assert_array_equal(image_to_array(m), image_to_array(w))
        else:
            assert [list(m.p) for _, m in got] == [w.p.tolist() for w in want]
    arrivals = [t for t, _ in listener.got['/left/image_rect']]
    # 2 periods of 0.1 s recorded, played at half speed: 0.4 s
    assert arrivals[-1] - arrivals[0] > 0.3


def test_play_loop_keeps_the_frame_rate(tmp_path, ros):
    """
    `play --loop` of a one-frame bag sends it at 10 Hz, not as fast as it can.

    Before: each pass began at once after the last, 270 images/s measured with ros2 topic hz
    (the node then reported images lost in transport).
    """
    from sensor_msgs.msg import Image
    bag_path = tmp_path / 'bag'
    assert bag.main(['make', '--dataset', 'motorcycle', '--out', str(bag_path)]) == 0
    listener = Listener(ros, 'test_bag_loop_listener', {'/left/image_rect': Image})
    proc = subprocess.Popen(
        [sys.executable, '-m', 'gcp_stereo_ros.tools.bag', 'play', '--in', str(bag_path),
         '--loop', '--wait-subscribers', '20'], cwd=REPO, env=os.environ, text=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        listener.wait(lambda: listener.counts()['/left/image_rect'] >= 12, '12 passes',
                      timeout=30)
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=20)
        listener.close()
    arrivals = np.array([t for t, _ in listener.got['/left/image_rect']])
    assert 0.07 < np.median(np.diff(arrivals)) < 0.15, np.diff(arrivals)


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
        assert stamp_of(live) == stamp_of(off) and live.header.frame_id == off.header.frame_id
        np.testing.assert_array_equal(image_to_array(live.image), image_to_array(off.image))
        assert [getattr(live, k) for k in scalars] == [getattr(off, k) for k in scalars]
        assert ([getattr(live.valid_window, k) for k in roi]
                == [getattr(off.valid_window, k) for k in roi])
    for (_, live), (_, off) in zip(listener.got['/gcp_mask'], offline['/gcp_mask'], strict=True):
        np.testing.assert_array_equal(image_to_array(live), image_to_array(off))


# ---- recordings: compressed, raw, any topic names ------------------------------------------
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


def info_msg(stamp, fields, frame_id):
    return TYPES.CameraInfo(
        header=stamped_header(stamp, frame_id), binning_x=0, binning_y=0,
        roi=TYPES.RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0,
                                   do_rectify=False), **fields)


def raw_recording(path, pair, names=('image_raw',)):
    """Write a bag as a camera driver records it: /cam/<side>/<name>, /cam/<side>/camera_info."""
    topics = {}
    for side in ('left', 'right'):  # camera_info first, as the node would have it
        topics[f'/cam/{side}/camera_info'] = (INFO, [
            (s, info_msg(s, pair.info[side], f'cam_{side}_optical_frame')) for s in (1, 2)])
    for side in ('left', 'right'):
        for name in names:
            fields = array_to_image_fields(pair.raw[side], 'rgb8')
            topics[f'/cam/{side}/{name}'] = (IMAGE, [
                (s, TYPES.Image(header=stamped_header(s, f'cam_{side}_optical_frame'), **fields))
                for s in (1, 2)])
    write_bag(path, topics)
    return path


def test_run_rectifies_a_raw_recording(tmp_path, distorted_pair):
    """
    Rectifying the recorded raw pair gives back the disparity of the rectified original.

    Measured at this size: 1.7 % of the interior pixels more than 1 px off, mean 0.27 px
    (interpolating twice); the raw pair matched without rectification: 92 %, mean 9.6 px.
    """
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({'/**': {'ros__parameters': {
        'max_disparity': 32, 'use_gcp': False}}}))
    bag_in = raw_recording(tmp_path / 'raw', distorted_pair)
    original = StereoPipeline(config_from_params({'max_disparity': 32, 'use_gcp': False}))(
        distorted_pair.rect['left'], distorted_pair.rect['right']).disparity
    inner = np.zeros(original.shape, bool)
    inner[12:-12, 32 + 12:-12] = True
    off = {}
    for rectify in (True, False):
        out = tmp_path / f'out_{rectify}'
        proc = cli('run', '--in', bag_in, '--out', out, '--params', params,
                   *(['--rectify'] if rectify else []), '--outputs', 'disparity,depth,points2')
        assert proc.returncode == 0, proc.stderr
        assert '/cam/left/image_raw + /cam/right/image_raw' in proc.stdout
        msgs, _ = read_bag(out)
        assert len(msgs['/cam/disparity']) == 2  # outputs under the pair's namespace
        (_, disp_msg), (_, depth_msg), (_, points_msg) = (
            msgs[f'/cam/{t}'][0] for t in ('disparity', 'depth', 'points2'))
        disp = image_to_array(disp_msg.image)
        disp[disp < disp_msg.min_disparity] = np.nan
        valid = inner & np.isfinite(disp) & np.isfinite(original)
        diff = np.abs(disp - original)[valid]
        off[rectify] = (diff > 1).mean(), diff.mean()
        assert disp_msg.header.frame_id == 'cam_left_optical_frame'
        assert (disp_msg.f, disp_msg.t) == (distorted_pair.f, pytest.approx(0.2))
        depth = np.frombuffer(depth_msg.data, '<f4').reshape(167, 247)  # NaN: no depth
        assert depth_msg.encoding == '32FC1'
        positive = np.isfinite(disp) & (disp > 0)
        np.testing.assert_allclose(depth[positive], 330 * 0.2 / disp[positive], rtol=1e-6)
        assert np.isnan(depth[~positive]).all()
        assert (points_msg.height, points_msg.width, points_msg.point_step) == (167, 247, 32)
    assert off[True][0] < 0.05 and off[True][1] < 0.6, off
    assert off[False][0] > 0.5, off  # the comparison can tell


def test_run_finds_the_stereo_pair_or_says_why(tmp_path, distorted_pair, capsys):
    two = raw_recording(tmp_path / 'two', distorted_pair, names=('image_raw', 'image_color'))
    out = tmp_path / 'out'
    assert bag.main(['run', '--in', str(two), '--out', str(out)]) == 1
    err = capsys.readouterr().err
    assert ('more than one stereo pair of image topics' in err
            and '/cam/left/image_color + /cam/right/image_color' in err
            and '/cam/left/image_raw + /cam/right/image_raw' in err and '--left' in err), err
    assert bag.main(['run', '--in', str(two), '--out', str(out), '--left', '/cam/left/image_raw'
                     ]) == 1
    assert '--left and --right go together' in capsys.readouterr().err
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({'/**': {'ros__parameters': {
        'max_disparity': 16, 'use_gcp': False}}}))
    assert bag.main(['run', '--in', str(two), '--out', str(out), '--params', str(params),
                     '--left', '/cam/left/image_color', '--right', '/cam/right/image_color',
                     '--left-info', '/cam/left/camera_info', '--right-info',
                     '/cam/right/camera_info', '--outputs', 'disparity']) == 0
    msgs, _ = read_bag(out)
    assert len(msgs['/cam/disparity']) == 2 and '/cam/gcp_mask' not in msgs
    assert msgs['/cam/disparity'][0][1].t == pytest.approx(0.2)  # camera_info was read


def test_run_pairs_each_image_with_the_camera_info_of_its_stamp(tmp_path, distorted_pair):
    """
    Check a driver's recording that stores each camera_info after its image.

    No pair is lost, none rectified or scaled with another frame's calibration (here the
    second frame's baseline is 0.3 m, the first's 0.2 m).
    """
    topics = {}
    for side in ('left', 'right'):
        fields = array_to_image_fields(distorted_pair.raw[side], 'rgb8')
        frame_id = f'cam_{side}_optical_frame'
        topics[f'/cam/{side}/image_raw'] = (IMAGE, [
            (s * 100, TYPES.Image(header=stamped_header(s, frame_id), **fields))
            for s in (1, 2)])
        infos = []
        for s, baseline in ((1, 0.2), (2, 0.3)):
            info = dict(distorted_pair.info[side])
            if side == 'right':
                p = np.array(info['p'], float)
                p[3] = -distorted_pair.f * baseline
                info['p'] = p
            infos.append((s * 100 + 10, info_msg(s, info, frame_id)))  # recorded after
        topics[f'/cam/{side}/camera_info'] = (INFO, infos)
    write_bag(tmp_path / 'after', topics)
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({'/**': {'ros__parameters': {
        'max_disparity': 32, 'use_gcp': False}}}))
    proc = cli('run', '--in', tmp_path / 'after', '--out', tmp_path / 'out', '--params', params,
               '--rectify', '--outputs', 'disparity')
    assert proc.returncode == 0, proc.stderr
    assert 'camera_info' not in proc.stderr, proc.stderr
    msgs, _ = read_bag(tmp_path / 'out')
    got = [(stamp_of(m), m.t) for _, m in msgs['/cam/disparity']]
    assert got == [(1, pytest.approx(0.2)), (2, pytest.approx(0.3))]
