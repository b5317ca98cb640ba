"""The ROS 2 node with real rclpy: outputs, encodings, sync, live parameters, bad input."""
import threading
import time

import cv2
from gcp_stereo_ros.ros.node import GcpStereoNode
from gcp_stereo_ros.ros.params import config_from_params
from gcp_stereo_ros.ros.rosimage import array_to_image_fields, image_to_array
from gcp_stereo_ros.stereo.pipeline import StereoPipeline
import numpy as np
import pytest
from rcl_interfaces.srv import SetParameters
import rclpy
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image
from skimage import data
from stereo_msgs.msg import DisparityImage

MAX_DISP = 32


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

    def error_logs(self):
        """Return the node's error lines as the console shows them (rcutils writes to stderr)."""
        self.stderr += self.capfd.readouterr().err
        return [line for line in self.stderr.splitlines()
                if line.startswith('[ERROR]') and '[gcp_stereo_node]' in line]

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
    ok = harness.set_params(theta=0.6, P1=6.0, P2=100.0, paths=8, downsample=2)
    assert all(r.successful for r in ok)
    for values, reason in [
        ({'P2': 2.0}, 'P2'),
        ({'paths': 12}, 'paths'),
        ({'theta': 1.5}, 'theta'),
        ({'cost': 'ncc'}, 'cost'),
        ({'weights': '/no/such/weights.pt'}, '/no/such/weights.pt'),
        ({'window': 10}, 'window'),
        ({'bf16': 'maybe'}, 'bf16'),
        ({'downsample': 3}, 'downsample'),
        ({'device': 'cuda:7'}, "device 'cuda:7'"),
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
                 'bf16': False, 'downsample': 2}
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


@pytest.mark.parametrize('harness', [{'weights': '/no/such/weights.pt'}], indirect=True)
def test_missing_weights_file_is_logged_and_survived(harness, pair):
    harness.send_pair(*pair, 'rgb8', 40_000_000_000)
    wait_for(lambda: any('/no/such/weights.pt' in m and 'skipping pair' in m
                         for m in harness.error_logs()),
             'weights error on a pair')
    # fix it live: frames flow again
    assert all(r.successful for r in harness.set_params(weights=''))
    harness.send_pair(*pair, 'rgb8', 41_000_000_000)
    wait_for(lambda: harness.disparity, 'disparity with the shipped weights')
