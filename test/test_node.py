"""The ROS 2 node with real rclpy: outputs, encodings, sync, live parameters, bad input."""
import os
from pathlib import Path
import re
import signal
import subprocess
import sys
import threading
import time

import cv2
from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.ros.graph import start_node, stop
from gcp_stereo_ros.ros.node import GcpStereoNode
from gcp_stereo_ros.ros.params import config_from_params
from gcp_stereo_ros.ros.rosimage import array_to_image_fields, image_to_array
from gcp_stereo_ros.ros.worker import NewestWorker
from gcp_stereo_ros.stereo.pipeline import StereoPipeline
import numpy as np
import pytest
from rcl_interfaces.srv import SetParameters
import rclpy
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image
from skimage import data
from stereo_msgs.msg import DisparityImage

MAX_DISP = 32
NODE_SCRIPT = str(Path(sys.executable).with_name('gcp_stereo_node'))


@pytest.fixture(scope='module')
def pair():
    """Motorcycle at a third of its size: real texture, quick to match."""
    left, right, _ = data.stereo_motorcycle()
    return tuple(cv2.resize(im, (247, 167), interpolation=cv2.INTER_AREA) for im in (left, right))


class Harness:
    """The node under test and a peer node that publishes pairs and records what comes back."""

    def __init__(self, overrides, capfd):
        self.capfd, self.stderr = capfd, ''
        self.node = GcpStereoNode(
            parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])
        self.peer = Node('test_peer')
        self.pub = {
            s: self.peer.create_publisher(Image, f'{s}/image_rect', qos_profile_sensor_data)
            for s in ('left', 'right')}
        self.disparity, self.gcp = [], []
        self.peer.create_subscription(DisparityImage, 'disparity', self.disparity.append, 10)
        self.peer.create_subscription(Image, 'gcp_mask', self.gcp.append, 10)
        self.set_client = self.peer.create_client(SetParameters, '/gcp_stereo_node/set_parameters')
        self.executor = MultiThreadedExecutor(num_threads=3)
        self.executor.add_node(self.node)
        self.executor.add_node(self.peer)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        wait_for(lambda: all(p.get_subscription_count() for p in self.pub.values()), 'subscribers')
        assert self.set_client.wait_for_service(timeout_sec=10)

    def send(self, side, array, encoding, stamp_ns, changes=None):
        """Publish `array` as `encoding`, with Image fields then overwritten by `changes`."""
        fields = array_to_image_fields(array, encoding) if array is not None else {}
        msg = Image(**{**fields, 'data': bytes(fields.get('data', b''))})
        for key, value in (changes or {}).items():
            setattr(msg, key, value)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        msg.header.frame_id = 'left_camera'
        self.pub[side].publish(msg)

    def send_pair(self, left, right, encoding, stamp_ns, right_stamp_ns=None):
        self.send('left', left, encoding, stamp_ns)
        self.send('right', right, encoding, stamp_ns if right_stamp_ns is None else right_stamp_ns)

    def set_params(self, **values):
        req = SetParameters.Request(
            parameters=[Parameter(k, value=v).to_parameter_msg() for k, v in values.items()])
        future = self.set_client.call_async(req)
        wait_for(future.done, 'set_parameters response')
        return future.result().results

    def log(self, severity):
        """Return the node's `severity` lines as the console shows them (rcutils: stderr)."""
        self.stderr += self.capfd.readouterr().err
        return '\n'.join(line for line in self.stderr.splitlines()
                         if line.startswith(f'[{severity}]') and '[gcp_stereo_node]' in line)

    def error_logs(self):
        return self.log('ERROR').splitlines()

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self.peer.destroy_node()


def wait_for(condition, what, timeout=60.0):
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, f'timed out waiting for {what}'
        time.sleep(0.01)


def stamp_of(msg):
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def expected(overrides, left, right):
    result = StereoPipeline(config_from_params(overrides))(left, right)
    disp = result.disparity.copy()
    disp[np.isnan(disp)] = -1
    return disp, result


@pytest.fixture(scope='module')
def ros():
    rclpy.init()
    yield
    rclpy.shutdown()


@pytest.fixture
def harness(ros, request, capfd):
    overrides = {'max_disparity': MAX_DISP, **getattr(request, 'param', {})}
    h = Harness(overrides, capfd)
    h.overrides = overrides
    yield h
    h.close()


def test_pair_gives_pipeline_output(harness, pair):
    left, right = pair
    harness.send_pair(left, right, 'rgb8', 5_000_000_123)
    wait_for(lambda: harness.disparity and harness.gcp, 'disparity and gcp_mask')
    disp_msg, gcp_msg = harness.disparity[0], harness.gcp[0]
    want, result = expected(harness.overrides, left, right)
    assert stamp_of(disp_msg) == stamp_of(gcp_msg) == 5_000_000_123
    assert disp_msg.header.frame_id == 'left_camera'
    np.testing.assert_array_equal(image_to_array(disp_msg.image), want)
    np.testing.assert_array_equal(image_to_array(gcp_msg), result.gcp.astype(np.uint8) * 255)
    assert 0.3 < result.gcp.mean() < 0.95  # GCPs are a real subset: a wrong mask would show
    assert disp_msg.max_disparity == MAX_DISP - 1 and disp_msg.min_disparity == 0
    assert disp_msg.valid_window.x_offset == MAX_DISP - 1 + 4


@pytest.mark.parametrize('harness', [{'use_gcp': False}], indirect=True)
def test_every_encoding(harness, pair):
    left, right = pair
    gray = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in pair]
    inputs = {
        'mono8': gray,
        'mono16': [g.astype(np.uint16) * 257 for g in gray],
        'rgb8': [left, right],
        'bgr8': [left, right],  # array_to_image_fields takes RGB and writes BGR order
    }
    stamp = 10_000_000_000
    for encoding, (l_img, r_img) in inputs.items():
        stamp += 1_000_000
        harness.send_pair(l_img, r_img, encoding, stamp)
        wait_for(lambda: harness.disparity and stamp_of(harness.disparity[-1]) == stamp, encoding)
    for alpha_encoding in ('rgba8', 'bgra8'):  # 4-channel: built by hand, alpha must be ignored
        stamp += 1_000_000
        for side, img in (('left', left), ('right', right)):
            order = img if alpha_encoding == 'rgba8' else img[:, :, ::-1]
            rgba = np.dstack([order, np.full(img.shape[:2], 7, np.uint8)])
            harness.send(side, None, None, stamp, {
                'height': img.shape[0], 'width': img.shape[1], 'encoding': alpha_encoding,
                'step': img.shape[1] * 4, 'is_bigendian': 0, 'data': rgba.tobytes()})
        wait_for(lambda: harness.disparity and stamp_of(harness.disparity[-1]) == stamp,
                 alpha_encoding)
    got = [image_to_array(m.image) for m in harness.disparity]
    want_color, _ = expected(harness.overrides, left, right)
    want_gray, _ = expected(harness.overrides, *gray)
    np.testing.assert_array_equal(got[0], want_gray)
    np.testing.assert_array_equal(got[1], want_gray)  # 257 * v keeps the order of values
    for g in got[2:]:
        np.testing.assert_array_equal(g, want_color)


@pytest.mark.parametrize('harness', [{'use_gcp': False, 'max_disparity': 16}], indirect=True)
def test_exact_and_approximate_sync(harness, pair):
    left, right = pair

    def outputs(n):  # the newest pair wins, so wait for each expected output before going on
        wait_for(lambda: len(harness.disparity) >= n, f'{n} disparity messages')
        return [stamp_of(m) for m in harness.disparity]

    # no exact twin
    harness.send_pair(left, right, 'rgb8', 1_000_000_000, right_stamp_ns=1_000_500_000)
    harness.send('left', left, 'rgb8', 3_000_000_000)  # out of order: 3 s, then 2 s
    harness.send('left', left, 'rgb8', 2_000_000_000)
    harness.send('right', right, 'rgb8', 2_000_000_000)
    assert outputs(1) == [2_000_000_000]
    harness.send('right', right, 'rgb8', 3_000_000_000)  # the queued 3 s left image finds its twin
    assert outputs(2) == [2_000_000_000, 3_000_000_000]

    assert all(r.successful for r in harness.set_params(
        approximate_sync=True, approximate_sync_tolerance_seconds=0.01))
    # 20 ms: too far
    harness.send_pair(left, right, 'rgb8', 4_000_000_000, right_stamp_ns=4_020_000_000)
    # 4 ms: a pair
    harness.send_pair(left, right, 'rgb8', 5_000_000_000, right_stamp_ns=5_004_000_000)
    assert outputs(3)[2:] == [5_000_000_000]
    harness.send('right', right, 'rgb8', 6_003_000_000)  # right first, within tolerance
    harness.send('left', left, 'rgb8', 6_000_000_000)
    assert outputs(4)[3:] == [6_000_000_000]
    time.sleep(0.5)
    assert len(harness.disparity) == 4  # nothing from the unmatched stamps
    assert harness.node.stats['stale'] == 0


def test_set_parameters_live(harness, pair):
    left, right = pair
    ok = harness.set_params(theta=0.6, P1=6.0, P2=100.0, paths=8)
    assert all(r.successful for r in ok)
    for values, reason in [
        ({'P2': 2.0}, 'P2'),
        ({'paths': 12}, 'paths'),
        ({'theta': 1.5}, 'theta'),
        ({'cost': 'ncc'}, 'cost'),
        ({'weights': '/no/such/weights.pt'}, '/no/such/weights.pt'),
        ({'window': 10}, 'window'),
        ({'bf16': 'maybe'}, 'bf16'),
    ]:
        (result,) = harness.set_params(**values)[:1]
        assert not result.successful and reason in result.reason, (values, result.reason)
    assert harness.node.get_parameter('theta').value == 0.6
    for bf16 in (True, 'auto', False):  # true, false or 'auto': one parameter, two types
        assert all(r.successful for r in harness.set_params(bf16=bf16))
        assert harness.node.params.pipeline.config.bf16 == bf16
    harness.send_pair(left, right, 'rgb8', 7_000_000_000)
    wait_for(lambda: harness.disparity, 'disparity after set')
    overrides = {**harness.overrides, 'theta': 0.6, 'P1': 6.0, 'P2': 100.0, 'paths': 8,
                 'bf16': False}
    want, result = expected(overrides, left, right)
    np.testing.assert_array_equal(image_to_array(harness.disparity[-1].image), want)
    np.testing.assert_array_equal(image_to_array(harness.gcp[-1]),
                                  result.gcp.astype(np.uint8) * 255)

    # Switching cost loads SAD's defaults; values set after it (SetParameters applies a
    # request in order) or in the same atomic request are kept.
    assert all(r.successful for r in harness.set_params(cost='sad', P2=20.0))
    values = {n: harness.node.get_parameter(n).value
              for n in ('theta', 'P1', 'P2', 'c_hi', 'c_low')}
    assert values == {'theta': 0.45, 'P1': 0.02, 'P2': 20.0, 'c_hi': 5.0, 'c_low': 0.001}
    harness.send_pair(left, right, 'rgb8', 8_000_000_000)
    wait_for(lambda: stamp_of(harness.disparity[-1]) == 8_000_000_000,
             'disparity after cost switch')
    want, _ = expected({**overrides, 'cost': 'sad', **values}, left, right)
    np.testing.assert_array_equal(image_to_array(harness.disparity[-1].image), want)


def test_bad_input_is_logged_and_survived(harness, pair):
    left, right = pair
    small = np.ascontiguousarray(right[:100])
    gray = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)
    nan_img = gray.astype(np.float32)
    nan_img[5, 5] = np.nan
    bad = [
        (lambda s: (harness.send('left', left, 'rgb8', s),
                    harness.send('right', small, 'rgb8', s)), 'right image'),
        (lambda s: (harness.send('left', left, 'rgb8', s, {'encoding': 'yuv422'}),
                    harness.send('right', right, 'rgb8', s)), "unsupported encoding 'yuv422'"),
        (lambda s: (harness.send('left', left, 'rgb8', s, {'step': 10}),
                    harness.send('right', right, 'rgb8', s)), 'step 10'),
        (lambda s: (harness.send('left', left, 'rgb8', s,
                                 {'height': 0, 'width': 0, 'step': 0, 'data': b''}),
                    harness.send('right', right, 'rgb8', s)), 'empty'),
        (lambda s: (harness.send('left', nan_img, '32FC1', s),
                    harness.send('right', nan_img, '32FC1', s)), 'NaN'),
    ]
    for i, (send, reason) in enumerate(bad):
        send(20_000_000_000 + i)
        wait_for(lambda: any(reason in m for m in harness.error_logs()),
                 f'error log with {reason!r}')
    assert all('left/image_rect' in m for m in harness.error_logs())
    assert not harness.disparity
    harness.send_pair(left, right, 'rgb8', 30_000_000_000)  # and the node still works
    wait_for(lambda: harness.disparity, 'disparity after bad input')


def test_errors_are_rate_limited_by_reason(harness, pair):
    left, right = pair
    small = np.ascontiguousarray(right[:100])
    for i in range(12):  # 12 bad pairs at 20 Hz, one reason: one line
        harness.send('left', left, 'rgb8', 50_000_000_000 + i * 50_000_000)
        harness.send('right', small, 'rgb8', 50_000_000_000 + i * 50_000_000)
        time.sleep(0.05)
    wait_for(lambda: harness.node.errors + harness.node.stats['stale'] == 12, '12 errors')
    lines = harness.error_logs()
    assert len(lines) == 1 and 'skipping pair' in lines[0] and 'stamp 50000000000 ns' in lines[0]


def test_worker_survives_a_failure_to_publish(harness, pair):
    publish, failures = harness.node._pub_disp.publish, []

    def fail_once(msg):
        if not failures:
            failures.append(msg)
            raise RuntimeError('transport gone')
        publish(msg)
    harness.node._pub_disp.publish = fail_once
    harness.send_pair(*pair, 'rgb8', 60_000_000_000)
    wait_for(lambda: any('cannot publish the outputs: transport gone' in m
                         for m in harness.error_logs()), 'the publishing error')
    harness.send_pair(*pair, 'rgb8', 61_000_000_000)
    wait_for(lambda: harness.disparity, 'disparity after the failure')
    assert stamp_of(harness.disparity[-1]) == 61_000_000_000


def camera_info(stamp_ns, size, fx, cx, tx):
    info = CameraInfo(width=size[1], height=size[0])
    info.header.stamp.sec, info.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    info.p = [fx, 0.0, cx, tx, 0.0, fx, size[0] / 2, 0.0, 0.0, 0.0, 1.0, 0.0]
    return info


def test_camera_info_is_checked(harness, pair):
    left, right = pair
    size = left.shape[:2]
    pubs = {s: harness.peer.create_publisher(CameraInfo, f'{s}/camera_info',
                                             qos_profile_sensor_data) for s in ('left', 'right')}
    wait_for(lambda: all(p.get_subscription_count() for p in pubs.values()), 'camera_info subs')
    cases = [  # (right fx, left cx, right cx, right Tx), reason
        ((500.0, 120.0, 120.0, -50.0), None),
        ((500.0, float('nan'), 120.0, -50.0), 'NaN'),
        ((500.0, 120.0, 120.0, 0.0), 'baseline'),
        ((500.0, 120.0, 120.0, 30.0), 'baseline'),
        ((1e300, 120.0, 120.0, -1e300), 'float32'),
        ((500.0, 120.0, 420.0, -50.0), 'principal points differ by -300'),
    ]
    for i, ((fx, cx_left, cx_right, tx), reason) in enumerate(cases):
        stamp = 70_000_000_000 + i * 1_000_000_000
        pubs['left'].publish(camera_info(stamp, size, fx, cx_left, 0.0))
        pubs['right'].publish(camera_info(stamp, size, fx, cx_right, tx))
        wait_for(lambda: all(m is not None and stamp_of(m) == stamp
                             for m in harness.node.input.info.values()), 'camera_info')
        harness.send_pair(left, right, 'rgb8', stamp)
        if reason is None:
            wait_for(lambda: harness.disparity, 'disparity with camera_info')
            assert harness.disparity[-1].f == 500.0
            assert harness.disparity[-1].t == pytest.approx(0.1)
        else:
            wait_for(lambda: any(reason in m and 'camera_info' in m
                                 for m in harness.error_logs()), reason)
    pubs['left'].publish(camera_info(90_000_000_000, (size[0] + 2, size[1]), 500.0, 120.0, 0.0))
    pubs['right'].publish(camera_info(90_000_000_000, size, 500.0, 120.0, -50.0))
    wait_for(lambda: all(stamp_of(m) == 90_000_000_000
                         for m in harness.node.input.info.values()), 'camera_info')
    harness.send_pair(left, right, 'rgb8', 90_000_000_000)
    wait_for(lambda: any(f'left camera_info is for {size[1]}x{size[0] + 2} images' in m
                         for m in harness.error_logs()), 'the size mismatch')
    assert len(harness.disparity) == 1


def test_images_larger_than_the_shared_memory_segment_are_warned_about(harness):
    pub = harness.peer.create_publisher(CameraInfo, 'left/camera_info', qos_profile_sensor_data)
    wait_for(lambda: pub.get_subscription_count(), 'camera_info subscription')
    pub.publish(camera_info(1, (4320, 8192), 500.0, 4096.0, 0.0))  # 34 MiB as mono8
    wait_for(lambda: '8192x4320 images, 34 MiB' in harness.log('WARN'), 'the warning')
    assert 'larger than the 32 MiB shared-memory segment' in harness.log('WARN')


@pytest.mark.parametrize('harness', [{'memory_limit_mb': 64}], indirect=True)
def test_a_pair_over_the_memory_limit_is_refused(harness, pair):
    """
    Check that a pair over memory_limit_mb is refused and the node keeps serving.

    A 247x167 pair needs about 70 MB at max_disparity 240 (two uint16 volumes of 19 MB and
    the CNN's strip).
    """
    assert all(r.successful for r in harness.set_params(max_disparity=240))
    harness.send_pair(*pair, 'rgb8', 80_000_000_000)
    wait_for(lambda: any('247x167 at max_disparity 240 needs about' in m
                         for m in harness.error_logs()), 'the memory refusal')
    line, = harness.error_logs()
    assert 'over memory_limit_mb 64: lower max_disparity (at most' in line
    assert 'raise downsample' in line
    fits = int(line.split('(at most ')[1].split()[0])
    assert 100 < fits < 240
    assert all(r.successful for r in harness.set_params(max_disparity=fits))
    harness.send_pair(*pair, 'rgb8', 81_000_000_000)
    wait_for(lambda: harness.disparity, 'disparity within the limit')


def test_arrays_are_let_go_when_idle(harness, pair):
    harness.send_pair(*pair, 'rgb8', 85_000_000_000)
    wait_for(lambda: harness.disparity, 'disparity')
    assert harness.node.params.pipeline._workspace  # kept for the next frame ...
    wait_for(lambda: not harness.node.params.pipeline._workspace, 'arrays let go', 5)


@pytest.mark.parametrize('harness', [{'thetta': 0.5, 'use_gcp': False}], indirect=True)
def test_misspelled_and_useless_parameters_are_reported(harness):
    harness.set_params(use_gcp=True, theta=0.9)
    wait_for(lambda: 'selects no GCP' in harness.log('WARN'), 'theta warning')
    assert "ignoring unknown parameter(s) 'thetta' (did you mean 'theta'?)" in harness.log('WARN')
    (result,) = harness.set_params(device='cudafoo')
    assert not result.successful and 'cudafoo' in result.reason


@pytest.mark.parametrize('settings, reason', [
    ({'weights': '/no/such/weights.pt'}, '/no/such/weights.pt'),
    ({'device': 'cuda', 'use_gcp': False}, "device 'cuda': this machine has no CUDA GPU"),
    ({'theta': 'high'}, 'theta'),
])
def test_bad_start_up_settings_stop_the_node(ros, settings, reason):
    if 'device' in settings and torch_cuda():
        pytest.skip('a CUDA GPU is present')
    with pytest.raises(Exception, match=re.escape(reason)):
        GcpStereoNode(parameter_overrides=[Parameter(k, value=v) for k, v in settings.items()])


def torch_cuda():
    import torch
    return torch.cuda.is_available()


def test_console_script_refuses_bad_start_up_in_one_line(tmp_path):
    bad_yaml = tmp_path / 'bad.yaml'
    bad_yaml.write_text('gcp_stereo_node:\n  ros__parameters:\n    theta: [1,\n')
    for args, reason in [
        (['-p', 'weights:=/no/such/weights.pt'], 'GCP CNN weights not found: /no/such/weights.pt'),
        (['--params-file', str(tmp_path / 'missing.yaml')], 'missing.yaml'),
        (['--params-file', str(bad_yaml)], 'cannot read parameters file'),
    ]:
        proc = subprocess.run([NODE_SCRIPT, '--ros-args', *args], capture_output=True,
                              text=True, timeout=60)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr
        assert lines[0].startswith('gcp_stereo_node: error: cannot start: ') and reason in lines[0]


def cpu_seconds(pid):
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


@pytest.mark.parametrize('signals', [(signal.SIGINT, signal.SIGINT), (signal.SIGTERM,)])
def test_node_process_stops_within_2_s_mid_frame(ros, data_dir, signals):
    """
    Stop a node process in the middle of a long frame, by Ctrl-C twice or SIGTERM.

    Aloe at 1282x1110 takes several seconds (fp32 CNN); the node stops it between two rows
    of a kernel or two CNN layers.
    """
    frame = load_frame(data_dir, 'middlebury2006/fullsize_opencv-doc/Aloe')
    node = start_node(os.environ, {'max_disparity': 64})
    peer = rclpy.create_node('test_stop_peer')
    disparity = []
    peer.create_subscription(DisparityImage, 'disparity', disparity.append, 10)
    pubs = {s: peer.create_publisher(Image, f'{s}/image_rect', qos_profile_sensor_data)
            for s in ('left', 'right')}
    executor = MultiThreadedExecutor(num_threads=2)
    executor.add_node(peer)
    threading.Thread(target=executor.spin, daemon=True).start()

    def send(side, image, stamp_ns):
        fields = array_to_image_fields(image, 'rgb8')
        msg = Image(**{**fields, 'data': fields['data'].tobytes()})
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        pubs[side].publish(msg)
    try:
        wait_for(lambda: all(p.get_subscription_count() for p in pubs.values()), 'the node')
        crop = (slice(0, 200), slice(0, 300))
        deadline = time.monotonic() + 120
        while not disparity:  # warm-up (Numba and torch first calls), sent until it is through
            assert time.monotonic() < deadline, 'no disparity of the warm-up pair'
            stamp = time.time_ns()
            send('left', frame.left[crop], stamp)
            send('right', frame.right[crop], stamp)
            pause = time.monotonic() + 3
            while not disparity and time.monotonic() < pause:
                time.sleep(0.05)
        cpu = cpu_seconds(node.pid)
        big = time.time_ns()
        send('left', frame.left, big)
        send('right', frame.right, big)
        wait_for(lambda: cpu_seconds(node.pid) > cpu + 1.0, 'the node at work')
        start = time.monotonic()
        for sig in signals:
            node.send_signal(sig)
            time.sleep(0.1)
        code = node.wait(30)
        seconds = time.monotonic() - start
    finally:
        stop(node)
        executor.shutdown()
        peer.destroy_node()
    assert code == 0 and seconds < 2.0, (code, seconds)
    assert big not in map(stamp_of, disparity)  # nothing of the stopped frame


def test_worker_thread_outlives_any_exception():
    done, errors, idle = [], [], threading.Event()

    def process(x):
        done.append(1 / x)
    worker = NewestWorker(process, 'test_worker', errors.append, idle.set, idle_seconds=0.2)
    worker.put((0,))  # ZeroDivisionError
    wait_for(lambda: errors, 'the error', 5)
    worker.put((4,))
    wait_for(lambda: done == [0.25], 'the next item', 5)
    assert idle.wait(5)  # and on_idle once it has been idle for 0.2 s
    assert isinstance(errors[0], ZeroDivisionError) and worker.stop(5)
