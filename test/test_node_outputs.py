"""The ROS 2 node's outputs as consumers read them, its diagnostics, input kinds, load."""
import threading
import time

import cv2
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from gcp_stereo_ros.ros import diagnostics, messages
from gcp_stereo_ros.ros.camera import Rectifier, StereoModel
from gcp_stereo_ros.ros.params import config_from_params
from gcp_stereo_ros.ros.rosimage import (array_to_compressed_fields, array_to_image_fields,
                                         image_to_array)
from gcp_stereo_ros.stereo.cnn.int8 import int8_native
from gcp_stereo_ros.stereo.cnn.network import bf16_native
from gcp_stereo_ros.stereo.pipeline import StereoPipeline
import numpy as np
import pytest
from rclpy.qos import ReliabilityPolicy
from ros_helpers import (BASELINE, CX_OFFSET, expected, F, MAX_DISP, rectified_infos,
                         wait_for)
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2


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
        wait_for(lambda: points and messages.stamp_ns(points[-1].header) == stamp * 1_000_000_000,
                 'points2')
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
        wait_for(lambda: harness.newest_stamp() == stamp, 'disparity')
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
    auto = 'int8' if int8_native() else 'bf16' if bf16_native() else 'fp32'
    for changes, precision in (({'use_gcp': True}, auto),
                               ({'precision': 'fp32'}, 'fp32'), ({'precision': 'int8'}, 'int8'),
                               ({'use_gcp': False, 'precision': 'auto'}, 'not used')):
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
    while not (harness.disparity and harness.newest_stamp() >= first):
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
        wait_for(lambda: harness.newest_stamp() == stamp, fmt)
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
    assert {messages.stamp_ns(m.header) for m in harness.disparity} == {5_000_000_000}


@pytest.mark.parametrize('harness', [{'use_gcp': False}], indirect=True)
def test_a_busy_node_takes_no_images_then_the_newest(harness, pair, monkeypatch):
    """Input the node cannot use costs it nothing: while it works, it takes no images."""
    release = threading.Event()
    process = StereoPipeline.__call__
    monkeypatch.setattr(StereoPipeline, '__call__',
                        lambda pipe, *a, **k: release.wait(60) and process(pipe, *a, **k))
    harness.send_pair(*pair, 'rgb8', 1_000_000_000)
    wait_for(lambda: harness.node.busy, 'processing')
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
    assert harness.newest_stamp() == newest
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
    wait_for(lambda: harness.node.busy, 'processing')
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
