"""
The ROS 2 node with real rclpy.

Outputs, encodings, sync, live parameters, bad input; memory, start-up and shutdown.
"""
import itertools
import math
import os
import re
import signal
import subprocess
import threading
import time

import cv2
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.ros import diagnostics, messages
from gcp_stereo_ros.ros.camera import Rectifier, StereoModel
from gcp_stereo_ros.ros.graph import executable, start_node, stop
from gcp_stereo_ros.ros.node import GcpStereoNode
from gcp_stereo_ros.ros.params import config_from_params
from gcp_stereo_ros.ros.rosimage import (array_to_compressed_fields, array_to_image_fields,
                                         image_to_array)
from gcp_stereo_ros.ros.worker import NewestWorker
from gcp_stereo_ros.stereo.cnn import bf16_native
from gcp_stereo_ros.stereo.pipeline import StereoPipeline
from gcp_stereo_ros.tools.load import cpu_seconds
import numpy as np
import pytest
from rcl_interfaces.msg import Log
from rcl_interfaces.srv import SetParameters
import rclpy
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from skimage import data
from stereo_msgs.msg import DisparityImage

MAX_DISP = 32
NODE_SCRIPT = str(executable('gcp_stereo_node'))


@pytest.fixture(scope='module')
def pair():
    """Motorcycle at a third of its size: real texture, quick to match."""
    left, right, _ = data.stereo_motorcycle()
    return tuple(cv2.resize(im, (247, 167), interpolation=cv2.INTER_AREA) for im in (left, right))


class Harness:
    """
    The node under test and a peer node that publishes pairs and records what comes back.

    The node's log lines are read from /rosout, as `ros2 topic echo /rosout` shows them:
    polling captured stderr (pytest's capfd) while the worker thread logs loses the lines
    written between its read and its truncation of the capture file, now and then.
    """

    def __init__(self, overrides):
        self.logs = []
        self._marks = itertools.count()
        self.node = GcpStereoNode(
            parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])
        self.peer = Node('test_peer')
        self.peer.create_subscription(Log, '/rosout', self.logs.append, QoSProfile(
            depth=1000, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.pub = {s: self.peer.create_publisher(Image, topic, qos_profile_sensor_data)
                    for s, topic in self.node.input.topics().items()}
        self.pubs = {}
        self.disparity, self.gcp = [], []
        self.peer.create_subscription(DisparityImage, 'disparity', self.disparity.append, 10)
        self.peer.create_subscription(Image, 'gcp_mask', self.gcp.append, 10)
        self.set_client = self.peer.create_client(SetParameters, '/gcp_stereo_node/set_parameters')
        self.executor = MultiThreadedExecutor(num_threads=3)
        self.executor.add_node(self.node)
        self.executor.add_node(self.peer)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        wait_for(lambda: all(self.matched(p) for p in self.pub.values()), 'subscribers')
        assert self.set_client.wait_for_service(timeout_sec=10)

    def matched(self, pub):
        """
        Return True once `pub` and the node's subscriptions of its topic know each other.

        Discovery is not symmetric: the publisher may see the subscription before the
        subscription sees the publisher, and a best-effort reader drops what it receives
        from a writer it does not know yet.
        """
        subs = [s for s in self.node.subscriptions if s.topic_name == pub.topic_name]
        return pub.get_subscription_count() >= len(subs) > 0 and all(
            s.get_publisher_count() > 0 for s in subs)

    def send(self, side, array, encoding, stamp_ns, changes=None, frame_id='left_camera'):
        """Publish `array` as `encoding`, with Image fields then overwritten by `changes`."""
        fields = array_to_image_fields(array, encoding) if array is not None else {}
        msg = Image(**{**fields, 'data': bytes(fields.get('data', b''))})
        for key, value in (changes or {}).items():
            setattr(msg, key, value)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        msg.header.frame_id = frame_id
        self.pub[side].publish(msg)

    def listen(self, topic, cls, qos=10):
        """Return the list the messages of `topic` go to, once the node's publisher has us."""
        got = []
        self.peer.create_subscription(cls, topic, got.append, qos)
        if topic in self.node._pubs:
            wait_for(lambda: self.node._pubs[topic].get_subscription_count() > 0, topic)
        return got

    def publish(self, topic, msg, cls=None):
        """Publish `msg` on `topic` with the sensor-data QoS, once the node subscribes it."""
        if topic not in self.pubs:
            self.pubs[topic] = self.peer.create_publisher(cls or type(msg), topic,
                                                          qos_profile_sensor_data)
            wait_for(lambda: self.matched(self.pubs[topic]), f'{topic} matched')
        self.pubs[topic].publish(msg)

    def send_info(self, side, fields, stamp_ns):
        msg = CameraInfo(**fields)
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        self.publish(f'{side}/camera_info', msg)
        wait_for(lambda: self.node.input.info[side] is not None
                 and stamp_of(self.node.input.info[side]) == stamp_ns, f'{side} camera_info')

    def send_taken(self, side, array, encoding, stamp_ns):
        """Send, then wait until the node took it (its image subscriptions keep depth 1)."""
        taken = self.node.input.received[side]
        self.send(side, array, encoding, stamp_ns)
        wait_for(lambda: self.node.input.received[side] > taken, f'{side} image taken')

    def send_pair(self, left, right, encoding, stamp_ns, right_stamp_ns=None, **kwargs):
        self.send('left', left, encoding, stamp_ns, **kwargs)
        self.send('right', right, encoding,
                  stamp_ns if right_stamp_ns is None else right_stamp_ns, **kwargs)

    def set_params(self, values):
        req = SetParameters.Request(
            parameters=[Parameter(k, value=v).to_parameter_msg() for k, v in values.items()])
        future = self.set_client.call_async(req)
        wait_for(future.done, 'set_parameters response')
        return future.result().results

    def error_logs(self, level='ERROR'):
        """
        Return the texts of the node's log lines of `level` so far, in order.

        The node's logger sends a mark last; /rosout is reliable and keeps the order of one
        publisher, so once the mark is here, so is every line the node logged before it.
        """
        mark = f'test: logs up to here ({next(self._marks)})'
        self.node.get_logger().info(mark)
        wait_for(lambda: any(m.msg == mark for m in self.logs), 'the log mark', 10)
        return [m.msg for m in list(self.logs)
                if m.name == 'gcp_stereo_node' and m.level == getattr(Log, level)]

    def close(self):
        """
        Stop spinning, then destroy the nodes.

        Destroying a node that the spinning thread still uses is deferred by rclpy; the next
        harness's node would then log through this one's /rosout publisher (rcl keeps one per
        logger name), and nothing once that one goes.
        """
        self.executor.shutdown()
        self.thread.join(10)
        assert not self.thread.is_alive()
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


@pytest.fixture
def harness(ros, request):
    overrides = {'max_disparity': MAX_DISP, **getattr(request, 'param', {})}
    h = Harness(overrides)
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
    assert disp_msg.valid_window.x_offset == 4  # the window's half: no valid pixel left of it
    assert math.copysign(1.0, disp_msg.min_disparity) == 1.0  # 0.0, never -0.0


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

    # no exact twin; each image taken before the next of its side is sent (send_pair would
    # not wait, and a newer left image replaces one not yet taken: depth 1)
    harness.send_taken('left', left, 'rgb8', 1_000_000_000)
    harness.send_taken('right', right, 'rgb8', 1_000_500_000)
    harness.send_taken('left', left, 'rgb8', 3_000_000_000)  # out of order: 3 s, then 2 s
    harness.send_taken('left', left, 'rgb8', 2_000_000_000)
    harness.send('right', right, 'rgb8', 2_000_000_000)
    assert outputs(1) == [2_000_000_000]
    harness.send('right', right, 'rgb8', 3_000_000_000)  # the queued 3 s left image finds its twin
    assert outputs(2) == [2_000_000_000, 3_000_000_000]

    assert all(r.successful for r in harness.set_params(
        {'approximate_sync': True, 'approximate_sync_tolerance_seconds': 0.01}))
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
    ok = harness.set_params({'census.theta': 0.6, 'census.P1': 6.0, 'census.P2': 100.0,
                             'paths': 8, 'downsample': 2})
    assert all(r.successful for r in ok)
    for values, reason in [
        ({'paths': 12}, 'paths'),
        ({'census.theta': 1.5}, 'theta'),
        ({'cost': 'ncc'}, 'cost'),
        ({'weights': '/no/such/weights.pt'}, '/no/such/weights.pt'),
        ({'census.window': 10}, 'window'),
        ({'census.window': 13}, 'census.window'),
        ({'image_transport': 'theora'}, 'image_transport'),
        ({'bf16': 'maybe'}, "bf16 must be one of 'auto', 'true', 'false', got 'maybe'"),
        ({'bf16': 1}, "expected 'Type.STRING' got 'Type.INTEGER'"),  # rclpy's own check
        ({'bf16': 0.0}, "expected 'Type.STRING' got 'Type.DOUBLE'"),
        ({'downsample': 3}, 'downsample'),
        ({'device': 'cuda:7'}, "device 'cuda:7'"),
    ]:
        (result,) = harness.set_params(values)[:1]
        assert not result.successful and reason in result.reason, (values, result.reason)
    assert harness.node.get_parameter('census.theta').value == 0.6
    for bf16, field in ((True, True), ('auto', 'auto'), ('true', True), (False, False)):
        assert all(r.successful for r in harness.set_params({'bf16': bf16}))
        assert harness.node.params.pipeline.config.bf16 == field
        param = harness.node.get_parameter('bf16')  # one type, whatever was sent
        assert (param.type_, param.value) == (Parameter.Type.STRING, str(bf16).lower())
    harness.send_pair(left, right, 'rgb8', 7_000_000_000)
    wait_for(lambda: harness.disparity, 'disparity after set')
    overrides = {**harness.overrides, 'census.theta': 0.6, 'census.P1': 6.0,
                 'census.P2': 100.0, 'paths': 8, 'bf16': False, 'downsample': 2}
    want, result = expected(overrides, left, right)
    np.testing.assert_array_equal(image_to_array(harness.disparity[-1].image), want)
    np.testing.assert_array_equal(image_to_array(harness.gcp[-1]),
                                  result.gcp.astype(np.uint8) * 255)

    # Switching cost uses SAD's own values and changes no other parameter.
    assert all(r.successful for r in harness.set_params({'sad.P2': 20.0, 'cost': 'sad'}))
    names = ('theta', 'P1', 'P2', 'c_hi', 'c_low', 'gcp_plain_check', 'plain_check')
    assert {n: harness.node.get_parameter(f'census.{n}').value for n in names} == {
        'theta': 0.6, 'P1': 6.0, 'P2': 100.0, 'c_hi': 200.0, 'c_low': 2.0,
        'gcp_plain_check': True, 'plain_check': 1.5}
    assert {n: harness.node.get_parameter(f'sad.{n}').value for n in names} == {
        'theta': 0.2, 'P1': 0.02, 'P2': 20.0, 'c_hi': 5.0, 'c_low': 0.001,
        'gcp_plain_check': False, 'plain_check': 0.0}
    harness.send_pair(left, right, 'rgb8', 8_000_000_000)
    wait_for(lambda: stamp_of(harness.disparity[-1]) == 8_000_000_000,
             'disparity after cost switch')
    want, _ = expected({**overrides, 'cost': 'sad', 'sad.P2': 20.0}, left, right)
    np.testing.assert_array_equal(image_to_array(harness.disparity[-1].image), want)

    # Values that cross (as `ros2 param load` sets P1 before P2) are taken and wait.
    assert all(r.successful for r in harness.set_params({'sad.P1': 30.0}))
    assert harness.node.params.pipeline.config.p1 == 0.02  # the last consistent values
    assert harness.node.params.pending == ['sad: P2 (20.0) must be >= P1 (30.0)']
    assert any('waiting for that, the node keeps its last consistent values' in m
               for m in harness.error_logs('WARN'))
    assert harness.node.get_parameter('sad.P1').value == 30.0
    assert all(r.successful for r in harness.set_params({'sad.P2': 40.0}))
    config = harness.node.params.pipeline.config
    assert (config.p1, config.p2, harness.node.params.pending) == (30.0, 40.0, [])


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


# ---- outputs as consumers read them, diagnostics, input kinds, load ------------------------
F, BASELINE, CX_OFFSET = 210.0, 0.12, 2.5


def rectified_infos(shape, baseline=BASELINE):
    """Return the CameraInfo fields of a rectified pair, principal points CX_OFFSET apart."""
    h, w = shape[:2]
    infos = {}
    for side, cx, tx in (('left', w / 2, 0.0), ('right', w / 2 - CX_OFFSET, -F * baseline)):
        infos[side] = {'width': w, 'height': h, 'distortion_model': 'plumb_bob', 'd': [0.0] * 5,
                       'k': [F, 0.0, cx, 0.0, F, h / 2, 0.0, 0.0, 1.0],
                       'r': [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                       'p': [F, 0.0, cx, tx, 0.0, F, h / 2, 0.0, 0.0, 0.0, 1.0, 0.0]}
    return infos


def image_geometry_q(left_info, right_info):
    """Return the Q of image_geometry's StereoCameraModel::updateQ, written out here."""
    pl, pr = (np.reshape(i['p'], (3, 4)) for i in (left_info, right_info))
    fx, fy, cx, cy = pl[0, 0], pl[1, 1], pl[0, 2], pl[1, 2]
    tx = pr[0, 3] / pr[0, 0]  # -baseline
    return np.array([[fy * tx, 0, 0, -fy * cx * tx], [0, fx * tx, 0, -fx * cy * tx],
                     [0, 0, 0, fx * fy * tx], [0, 0, -fy, fy * (cx - pr[0, 2])]])


def floats(msg):
    """Return the float32 pixels of a 32FC1 Image, NaN included (image_to_array refuses NaN)."""
    assert msg.encoding == '32FC1' and msg.step == 4 * msg.width
    return np.frombuffer(msg.data, '<f4').reshape(msg.height, msg.width)


@pytest.mark.parametrize('harness', [{'use_gcp': False}], indirect=True)
def test_depth_and_points2_equal_opencv_reprojection(harness, pair, monkeypatch):
    left, right = pair
    h, w = left.shape[:2]
    infos = rectified_infos(left.shape)
    for side in ('left', 'right'):
        harness.send_info(side, infos[side], 1)
    depth_calls = []
    real_depth = StereoModel.depth
    monkeypatch.setattr(StereoModel, 'depth',
                        lambda model, d: depth_calls.append(1) or real_depth(model, d))
    harness.send_pair(left, right, 'rgb8', 2_000_000_000)
    wait_for(lambda: harness.disparity, 'disparity')
    assert not depth_calls  # nobody subscribes depth or points2: neither is computed
    depth, points = harness.listen('depth', Image), harness.listen('points2', PointCloud2)
    harness.send_pair(left, right, 'rgb8', 3_000_000_000)
    wait_for(lambda: depth and points and len(harness.disparity) == 2, 'depth and points2')
    raw = StereoPipeline(config_from_params(harness.overrides))(left, right).disparity

    disp_msg = harness.disparity[-1]  # as consumers read a DisparityImage: Z = f * t / d
    assert (disp_msg.f, disp_msg.t, disp_msg.delta_d) == (F, pytest.approx(BASELINE), 1 / 16)
    assert (disp_msg.min_disparity, disp_msg.max_disparity) == (-CX_OFFSET,
                                                                MAX_DISP - 1 - CX_OFFSET)
    np.testing.assert_array_equal(image_to_array(disp_msg.image),
                                  np.where(np.isnan(raw), -CX_OFFSET - 1, raw - CX_OFFSET))
    roi = disp_msg.valid_window  # the matching window inside the image
    assert (roi.x_offset, roi.y_offset, roi.width, roi.height) == (4, 4, w - 8, h - 8)
    for name, pub in harness.node._pubs.items():  # as image_pipeline's on Jazzy
        qos = pub.qos_profile
        assert (qos.reliability, qos.depth) == (ReliabilityPolicy.RELIABLE, 1), name
        assert harness.node.has_parameter(f'qos_overrides./{name}.publisher.depth')

    xyz = cv2.reprojectImageTo3D(raw, image_geometry_q(infos['left'], infos['right']))
    valid = np.isfinite(raw) & (raw > CX_OFFSET)
    assert 0.5 < valid.mean() < 1
    z = floats(depth[-1])
    assert depth[-1].header.frame_id == 'left_camera'
    np.testing.assert_allclose(z[valid], xyz[..., 2][valid], rtol=1e-5)
    assert np.isnan(z[~valid]).all()
    cloud = points[-1]
    assert (cloud.height, cloud.width, cloud.point_step, cloud.row_step, cloud.is_dense) == (
        h, w, 32, 32 * w, False)
    assert [(f.name, f.offset, f.datatype, f.count) for f in cloud.fields] == [
        ('x', 0, 7, 1), ('y', 4, 7, 1), ('z', 8, 7, 1), ('rgb', 16, 7, 1)]
    data = np.frombuffer(cloud.data, np.float32).reshape(h, w, 8)
    np.testing.assert_allclose(data[..., :3][valid], xyz[valid], rtol=1e-5, atol=1e-6)
    assert np.isnan(data[..., :3][~valid]).all()
    bgra = data[..., 4].copy().view(np.uint8).reshape(h, w, 4)  # packed as b, g, r, 0
    np.testing.assert_array_equal(bgra[..., :3], left[..., ::-1])
    assert not bgra[..., 3].any()

    for stamp, change, step, names in ((4, {'avoid_point_cloud_padding': True}, 16, 'xyzr'),
                                       (5, {'use_color': False}, 12, 'xyz'),
                                       (6, {'avoid_point_cloud_padding': False}, 16, 'xyz')):
        assert all(r.successful for r in harness.set_params(change))
        harness.send_pair(left, right, 'rgb8', stamp * 1_000_000_000)
        wait_for(lambda: points and stamp_of(points[-1]) == stamp * 1_000_000_000, 'points2')
        assert points[-1].point_step == step
        assert ''.join(f.name[0] for f in points[-1].fields) == names
        assert [f.offset for f in points[-1].fields] == [0, 4, 8, 12][:len(names)]


@pytest.mark.parametrize('harness', [{'use_gcp': False, 'lr_check': True}], indirect=True)
def test_disparity_color_only_while_subscribed(harness, pair, monkeypatch):
    """bgr8 for image panels: jet over 0 .. max_disparity - 1, black where invalid."""
    calls, real = [], messages.color_map
    monkeypatch.setattr(messages, 'color_map', lambda *a: calls.append(1) or real(*a))
    harness.send_pair(*pair, 'rgb8', 1_000_000_000)
    wait_for(lambda: harness.disparity, 'disparity')
    assert not calls  # nobody subscribes: not computed
    colored = harness.listen('disparity_color', Image)
    harness.send_pair(*pair, 'rgb8', 2_000_000_000)
    wait_for(lambda: colored, 'disparity_color')
    msg = colored[0]
    assert (msg.encoding, msg.height, msg.width, msg.step) == ('bgr8', 167, 247, 3 * 247)
    bgr = np.frombuffer(msg.data, np.uint8).reshape(167, 247, 3)
    raw = StereoPipeline(config_from_params(harness.overrides))(*pair).disparity
    jet = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_JET)[:, 0]
    valid = ~np.isnan(raw)
    want = jet[np.clip(raw[valid] * np.float32(255 / (MAX_DISP - 1)), 0, 255).astype(np.uint8)]
    np.testing.assert_array_equal(bgr[valid], want)
    assert (bgr[~valid] == 0).all() and 0.3 < valid.mean() < 1.0
    assert tuple(jet[0]) == (128, 0, 0) and tuple(jet[255]) == (0, 0, 128)  # B first


@pytest.mark.parametrize('harness', [{'use_gcp': False}], indirect=True)
def test_no_calibration_gives_one_warning_and_no_depth(harness, pair):
    left, right = pair
    depth = harness.listen('depth', Image)
    harness.send_pair(left, right, 'rgb8', 1_000_000_000, frame_id='')
    wait_for(lambda: harness.disparity, 'disparity without camera_info')
    for side, fields in rectified_infos(left.shape, baseline=-BASELINE).items():
        harness.send_info(side, fields, 2_000_000_000)
    for stamp in (3_000_000_000, 4_000_000_000):
        harness.send_pair(left, right, 'rgb8', stamp)
        wait_for(lambda: stamp_of(harness.disparity[-1]) == stamp, 'disparity')
    warnings = harness.error_logs('WARN')
    assert sum('no depth or points2: no left camera_info received' in m for m in warnings) == 1
    assert sum('camera_info ignored (no f, t, depth or points2): baseline T' in m
               and 'not positive' in m for m in warnings) == 1, warnings
    assert sum('/left/image_rect: empty frame_id' in m for m in warnings) == 1
    assert not depth and harness.disparity[-1].t == 0.0  # no depth, no made-up geometry


def status_of(array_msg):
    status, = array_msg.status
    return status, {kv.key: kv.value for kv in status.values}


def diagnostics_of_one_pair(harness, pair):
    """Return the /diagnostics arrays received until one says a pair was processed."""
    diagnostics = harness.listen('/diagnostics', DiagnosticArray)
    harness.send_pair(*pair, 'rgb8', 1_000_000_000)
    wait_for(lambda: harness.disparity, 'disparity')
    wait_for(lambda: any(status_of(d)[1]['pairs processed'] == '1' for d in diagnostics),
             'diagnostics after one pair')
    return diagnostics


@pytest.mark.parametrize('harness', [{'use_gcp': False, 'use_sim_time': True}], indirect=True)
def test_sim_time_without_a_clock_gives_no_latency(harness, pair):
    """Before a /clock the node's time is 0: the latency was -(the stamp), now it is empty."""
    diagnostics = diagnostics_of_one_pair(harness, pair)
    assert {status_of(d)[1]['latency s (stamp to publish), mean'] for d in diagnostics} == {''}


@pytest.mark.parametrize('harness', [{'use_gcp': False}], indirect=True)
def test_diagnostics_say_what_is_wrong(harness, pair):
    left, right = pair
    diagnostics = diagnostics_of_one_pair(harness, pair)
    status, values = status_of(diagnostics[-1])
    assert status.level == DiagnosticStatus.OK and status.name == 'gcp_stereo_node: stereo'
    assert {'left images/s', 'right images/s', 'pairs processed/s', 'pairs dropped stale',
            'latency s (stamp to publish), mean', 'images dropped unmatched, left', 'errors',
            'device', 'weights'} <= set(values)
    assert (values['device'], values['left topic']) == ('cpu', '/left/image_rect')
    assert values['CNN descriptors'] == 'not used'  # the harness runs without GCPs
    for changes, precision in (({'use_gcp': True}, 'bfloat16' if bf16_native() else 'float32'),
                               ({'bf16': False}, 'float32'), ({'bf16': True}, 'bfloat16'),
                               ({'use_gcp': False, 'bf16': 'auto'}, 'not used')):
        assert all(r.successful for r in harness.set_params(changes))
        values = {kv.key: kv.value for kv in harness.node.diagnostics.status().values}
        assert values['CNN descriptors'] == precision, changes

    def warned(*words):
        return any(status_of(d)[0].level == DiagnosticStatus.WARN
                   and all(w in status_of(d)[0].message for w in words) for d in diagnostics)

    stamp = 2_000_000_000  # only the left camera publishes
    while not warned('no image on /right/image_rect', '/left/image_rect gets'):
        assert stamp < 12_000_000_000, [status_of(d)[0].message for d in diagnostics]
        harness.send('left', left, 'rgb8', stamp)
        stamp += 200_000_000
        time.sleep(0.2)
    while not warned('both arrive but their stamps never match', 'approximate_sync'):
        assert stamp < 24_000_000_000, [status_of(d)[0].message for d in diagnostics]
        harness.send_pair(left, right, 'rgb8', stamp, right_stamp_ns=stamp + 30_000_000)
        stamp += 200_000_000
        time.sleep(0.2)
    # as the warning says: approximate_sync, its tolerance 0 (the closest stamps)
    assert all(r.successful for r in harness.set_params({'approximate_sync': True}))
    first = stamp
    while not (harness.disparity and stamp_of(harness.disparity[-1]) >= first):
        assert stamp < first + 10_000_000_000, 'no pair of the closest stamps'
        harness.send_pair(left, right, 'rgb8', stamp, right_stamp_ns=stamp + 30_000_000)
        stamp += 200_000_000
        time.sleep(0.2)


@pytest.mark.parametrize('harness', [{'use_gcp': False}], indirect=True)
def test_compressed_input(harness, pair):
    left, right = pair
    assert all(r.successful for r in harness.set_params({'image_transport': 'compressed'}))
    assert harness.node.input.topics() == {'left': '/left/image_rect/compressed',
                                           'right': '/right/image_rect/compressed'}
    want, _ = expected(harness.overrides, left, right)
    for stamp, fmt in ((1_000_000_000, 'png'), (2_000_000_000, 'jpeg')):
        for side, image in (('left', left), ('right', right)):
            fields = array_to_compressed_fields(image, fmt)
            msg = CompressedImage(format=fields['format'], data=fields['data'].tobytes())
            msg.header.stamp.sec = stamp // 1_000_000_000
            harness.publish(f'{side}/image_rect/compressed', msg)
        wait_for(lambda: harness.disparity and stamp_of(harness.disparity[-1]) == stamp, fmt)
    png, jpeg = (image_to_array(m.image) for m in harness.disparity)
    np.testing.assert_array_equal(png, want)  # lossless: exactly the raw images' disparity
    assert 0 < (np.abs(jpeg - want) > 1).mean() < 0.15  # lossy, and still the same scene
    bad = CompressedImage(format='rgb8; png compressed bgr8', data=b'not a png at all')
    bad.header.stamp.sec = 3
    for side in ('left', 'right'):
        harness.publish(f'{side}/image_rect/compressed', bad)
    wait_for(lambda: any('/left/image_rect/compressed: 16 bytes of format' in m
                         for m in harness.error_logs()), 'decode error')


@pytest.mark.parametrize('harness', [{'use_gcp': False, 'rectify': True}], indirect=True)
def test_rectify_raw_input(harness, distorted_pair):
    """The node rectifies as `gcp-stereo-bag run --rectify` (accuracy: test_bag)."""
    assert harness.node.input.topics() == {'left': '/left/image_raw',
                                           'right': '/right/image_raw'}
    rectifier, rectified = Rectifier(), {}
    for side in ('left', 'right'):
        info = CameraInfo(**distorted_pair.info[side])
        harness.send_info(side, distorted_pair.info[side], 1)
        rectified[side] = rectifier(side, info, distorted_pair.raw[side])
        fields = array_to_image_fields(distorted_pair.raw[side], 'rgb8')
        msg = Image(**{**fields, 'data': fields['data'].tobytes()})
        msg.header.stamp.sec = 2
        harness.publish(f'{side}/image_raw', msg)
    wait_for(lambda: harness.disparity, 'disparity of the raw pair')
    want, _ = expected(harness.overrides, rectified['left'], rectified['right'])
    np.testing.assert_array_equal(image_to_array(harness.disparity[-1].image), want)


@pytest.mark.parametrize('harness', [{'use_gcp': False}], indirect=True)
def test_a_looped_one_frame_bag_gives_output_on_every_pass(harness, pair):
    for n in range(1, 4):  # what `play --loop` sends: the same stamps again and again
        harness.send_pair(*pair, 'rgb8', 5_000_000_000)
        wait_for(lambda: len(harness.disparity) == n, f'output of pass {n}')
    assert {stamp_of(m) for m in harness.disparity} == {5_000_000_000}


@pytest.mark.parametrize('harness', [{'use_gcp': False}], indirect=True)
def test_a_busy_node_takes_no_images_then_the_newest(harness, pair, monkeypatch):
    """Input the node cannot use costs it nothing: while it works, it takes no images."""
    release = threading.Event()
    process = StereoPipeline.__call__
    monkeypatch.setattr(StereoPipeline, '__call__',
                        lambda pipe, *a, **k: release.wait(60) and process(pipe, *a, **k))
    harness.send_pair(*pair, 'rgb8', 1_000_000_000)
    wait_for(lambda: not harness.node._worker.idle, 'processing')
    taken = dict(harness.node.input.received)
    newest = 0
    for i in range(50):  # 50 pairs while the node works
        newest = 2_000_000_000 + i * 10_000_000
        harness.send_pair(*pair, 'rgb8', newest)
        time.sleep(0.01)
    time.sleep(0.5)
    assert harness.node.input.received == taken
    release.set()
    wait_for(lambda: len(harness.disparity) == 2, 'the newest pair')
    assert stamp_of(harness.disparity[-1]) == newest
    assert {s: harness.node.input.received[s] - taken[s] for s in taken} == {'left': 1, 'right': 1}


@pytest.mark.parametrize('harness', [{'use_gcp': False}], indirect=True)
def test_a_slow_frame_is_no_missing_pair_and_arrivals_are_counted(harness, pair, monkeypatch):
    """A frame longer than the no-pair window while a camera streams: OK, with its true rate."""
    monkeypatch.setattr(diagnostics, 'NO_PAIR_SECONDS', 1.0)
    release = threading.Event()
    process = StereoPipeline.__call__
    monkeypatch.setattr(StereoPipeline, '__call__',
                        lambda pipe, *a, **k: release.wait(60) and process(pipe, *a, **k))
    statuses, stamp = [], 1_000_000_000
    harness.send_pair(*pair, 'rgb8', stamp)
    wait_for(lambda: not harness.node._worker.idle, 'processing')
    end = time.monotonic() + 3.0  # three times the window, 20 pairs a second
    while time.monotonic() < end:
        stamp += 50_000_000
        harness.send_pair(*pair, 'rgb8', stamp)
        statuses.append(harness.node.diagnostics.status())
        time.sleep(0.05)
    release.set()
    wait_for(lambda: len(harness.disparity) == 2, 'the newest pair')
    assert all(s.level == DiagnosticStatus.OK for s in statuses), [s.message for s in statuses]
    assert {s.message for s in statuses} == {'processing'}
    rate = float(status_of(DiagnosticArray(status=[harness.node.diagnostics.status()]))[1][
        'left images/s'])
    assert harness.node.input.received['left'] == 2  # taken: the first and the newest
    assert harness.node.input.arrived['left'] > 40  # arrived: all the camera sent
    assert rate > 10, rate  # 20/s sent; a window of at least 1 s, at most 3 s + 1 s


# ---- reliability: errors, memory, start-up, shutdown --------------------------------------
def test_errors_are_rate_limited_by_reason(harness, pair):
    left, right = pair
    small = np.ascontiguousarray(right[:100])
    for i in range(12):  # 12 bad pairs at 20 Hz, one reason: one line
        harness.send('left', left, 'rgb8', 50_000_000_000 + i * 50_000_000)
        harness.send('right', small, 'rgb8', 50_000_000_000 + i * 50_000_000)
        time.sleep(0.05)
    wait_for(lambda: harness.node.errors >= 1 and harness.node._worker.idle, 'the errors')
    time.sleep(0.5)
    assert harness.node.errors >= 6  # the node takes the newest pair when idle
    lines = harness.error_logs()
    assert len(lines) == 1 and 'skipping pair' in lines[0] and 'stamp 50000000000 ns' in lines[0]


def test_worker_survives_a_failure_to_publish(harness, pair):
    publisher = harness.node._pubs['disparity']
    publish, failures = publisher.publish, []

    def fail_once(msg):
        if not failures:
            failures.append(msg)
            raise RuntimeError('transport gone')
        publish(msg)
    publisher.publish = fail_once
    harness.send_pair(*pair, 'rgb8', 60_000_000_000)
    wait_for(lambda: any('cannot publish the outputs: transport gone' in m
                         for m in harness.error_logs()), 'the publishing error')
    harness.send_pair(*pair, 'rgb8', 61_000_000_000)
    wait_for(lambda: harness.disparity, 'disparity after the failure')
    assert stamp_of(harness.disparity[-1]) == 61_000_000_000


def test_worker_thread_outlives_any_exception():
    done, errors, quiet = [], [], threading.Event()

    def process(x):
        done.append(1 / x)
    worker = NewestWorker(process, 'test_worker', errors.append, on_quiet=quiet.set,
                          quiet_seconds=0.2)
    worker.put((0,))  # ZeroDivisionError
    wait_for(lambda: errors, 'the error', 5)
    worker.put((4,))
    wait_for(lambda: done == [0.25], 'the next item', 5)
    assert quiet.wait(5)  # and on_quiet once it has been quiet for 0.2 s
    assert isinstance(errors[0], ZeroDivisionError) and worker.stop(5)


@pytest.mark.parametrize('harness', [{'use_gcp': False}], indirect=True)
def test_bad_camera_info_is_said_and_ignored(harness, pair):
    """A camera_info that cannot be right is named in a warning; no f, t, depth from it."""
    left, right = pair
    good = rectified_infos(left.shape)
    cases = [  # (side, P index or field, value, reason)
        ('right', 2, float('nan'), 'P is not finite'),
        ('right', 3, 0.0, 'baseline T = -P_right[0,3] / P_right[0,0] = 0 is not positive'),
        ('right', 2, left.shape[1] / 2 - 300, 'left principal point is 300 px right of the right'),
        ('left', 0, 1e300, 'does not fit the float32'),
        ('right', 'height', left.shape[0] + 2, 'right camera_info is for 247x169 images'),
    ]
    for i, (side, where, value, reason) in enumerate(cases):
        infos = {s: dict(fields) for s, fields in good.items()}
        if isinstance(where, str):
            infos[side][where] = value
        else:
            infos[side]['p'] = [value if j == where else v for j, v in enumerate(good[side]['p'])]
        stamp = (i + 1) * 1_000_000_000
        for s in ('left', 'right'):
            harness.send_info(s, infos[s], stamp)
        harness.send_pair(left, right, 'rgb8', stamp)
        wait_for(lambda: harness.disparity and stamp_of(harness.disparity[-1]) == stamp, reason)
        assert (harness.disparity[-1].f, harness.disparity[-1].t) == (0.0, 0.0)
        wait_for(lambda: any('camera_info ignored' in m and reason in m
                             for m in harness.error_logs('WARN')), reason)


def test_images_larger_than_the_shared_memory_segment_are_warned_about(harness):
    info = rectified_infos((4320, 8192))['left']  # 34 MiB even as mono8
    harness.send_info('left', info, 1)
    wait_for(lambda: any('8192x4320 images, 34 MiB' in m for m in harness.error_logs('WARN')),
             'the warning')
    assert any('larger than the 32 MiB shared-memory segment' in m
               for m in harness.error_logs('WARN'))


@pytest.mark.parametrize('harness', [{'memory_limit_mb': 96}], indirect=True)
def test_a_pair_over_the_memory_limit_is_refused(harness, pair):
    """
    Check that a pair over memory_limit_mb is refused and the node keeps serving.

    A 247x167 pair needs about 168 MB at max_disparity 240 (two uint16 volumes of 19 MB, the
    CNN filter's rows of 57 MB, and the CNN's strips, eight layers' worth with the heap's
    slack: memory.STRIP_LAYERS).
    """
    assert all(r.successful for r in harness.set_params({'max_disparity': 240}))
    harness.send_pair(*pair, 'rgb8', 80_000_000_000)
    wait_for(lambda: any('247x167 at max_disparity 240 needs about' in m
                         for m in harness.error_logs()), 'the memory refusal')
    line, = harness.error_logs()
    assert 'over memory_limit_mb 96: lower max_disparity (at most' in line
    assert 'raise downsample' in line
    fits = int(line.split('(at most ')[1].split()[0])
    assert 40 < fits < 240  # 55
    assert all(r.successful for r in harness.set_params({'max_disparity': fits}))
    harness.send_pair(*pair, 'rgb8', 81_000_000_000)
    wait_for(lambda: harness.disparity, 'disparity within the limit')


def test_arrays_are_let_go_when_quiet(harness, pair):
    harness.send_pair(*pair, 'rgb8', 85_000_000_000)
    wait_for(lambda: harness.disparity, 'disparity')
    assert harness.node.params.pipeline._workspace  # kept for the next frame ...
    wait_for(lambda: not harness.node.params.pipeline._workspace, 'arrays let go', 5)


@pytest.mark.parametrize('harness', [{'use_gcp': False}], indirect=True)
def test_a_theta_no_pixel_can_reach_is_warned_about(harness):
    harness.set_params({'use_gcp': True, 'census.theta': 0.97})  # the weights reach 0.961
    wait_for(lambda: any('theta 0.97 selects no GCP' in m for m in harness.error_logs('WARN')),
             'theta warning')


@pytest.mark.parametrize('settings, reason', [
    ({'weights': '/no/such/weights.pt'}, '/no/such/weights.pt'),
    ({'device': 'cuda', 'use_gcp': False}, "device 'cuda'"),
    ({'census.theta': 'high'}, 'census.theta'),
    ({'thetta': 0.5}, "unknown parameter(s) ['thetta'] (did you mean 'census.theta'?)"),
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
    bad_yaml.write_text('gcp_stereo_node:\n  ros__parameters:\n    max_disparity: [1,\n')
    for args, reason in [
        (['-p', 'weights:=/no/such/weights.pt'], 'GCP CNN weights not found: /no/such/weights.pt'),
        (['--params-file', str(tmp_path / 'missing.yaml')], 'missing.yaml'),
        (['--params-file', str(bad_yaml)], 'cannot read parameters file'),
    ]:
        proc = subprocess.run([NODE_SCRIPT, '--ros-args', *args], capture_output=True,
                              text=True, timeout=60)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr
        assert lines[0].startswith('gcp_stereo_node: error: cannot start: ')
        assert reason in lines[0], lines[0]


@pytest.mark.parametrize('signals, gap', [((signal.SIGINT, signal.SIGINT), 0.1),
                                          ((signal.SIGINT, signal.SIGINT), 0.0),
                                          ((signal.SIGTERM,), 0.0)])
def test_node_process_stops_within_2_s_mid_frame(ros, data_dir, signals, gap):
    """
    Stop a node process in the middle of a long frame, by Ctrl-C twice or SIGTERM.

    Aloe at 1282x1110 takes seconds; the node stops it between two rows of a kernel or two
    CNN layers. Two Ctrl-C at once are what `ros2 launch` gives (the terminal's, then its
    own). With the real launch the second one once (1 run of 17) came while the node was
    already stopping and aborted its exit; that window is too short to hit here on purpose
    (6 of 6 runs passed before the fix), so this checks the pair stops cleanly.
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
            time.sleep(gap)
        code = node.wait(30)
        seconds = time.monotonic() - start
    finally:
        stop(node)
        executor.shutdown()
        peer.destroy_node()
    assert code == 0 and seconds < 2.0, (code, seconds)
    assert big not in map(stamp_of, disparity)  # nothing of the stopped frame


@pytest.mark.parametrize('harness', [{'use_gcp': False}], indirect=True)
def test_each_pair_gets_the_camera_info_of_its_stamp(harness, pair):
    """A driver that publishes each camera_info after its image: every pair has its own."""
    left, right = pair
    for i, baseline in enumerate((0.12, 0.3, 0.2)):
        stamp = (i + 1) * 1_000_000_000
        harness.send_taken('left', left, 'rgb8', stamp)
        harness.send_taken('right', right, 'rgb8', stamp)
        infos = rectified_infos(left.shape, baseline)
        for side in ('left', 'right'):
            harness.send_info(side, infos[side], stamp)
        wait_for(lambda: len(harness.disparity) == i + 1, f'disparity {i}')
    got = [(stamp_of(m), m.t) for m in harness.disparity]
    # the first pair waited for its camera_info only once their stamps were seen to follow the
    # images'; it went uncalibrated (t = 0)
    assert got[1:] == [(2_000_000_000, pytest.approx(0.3)), (3_000_000_000, pytest.approx(0.2))]
    assert got[0][0] == 1_000_000_000
