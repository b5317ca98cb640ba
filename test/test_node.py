"""
The ROS 2 node with real rclpy: its outputs, encodings, sync, live parameters, bad input.

The other node tests: test_node_outputs.py, test_node_reliability.py.
"""
import math
import time

import cv2
from gcp_stereo_ros.ros import messages
from gcp_stereo_ros.ros.rosimage import image_to_array
import numpy as np
import pytest
from ros_helpers import expected, MAX_DISP, wait_for


def test_pair_gives_pipeline_output(harness, pair):
    left, right = pair
    harness.send_pair(left, right, 'rgb8', 5_000_000_123)
    wait_for(lambda: harness.disparity and harness.gcp, 'disparity and gcp_mask')
    disp_msg, gcp_msg = harness.disparity[0], harness.gcp[0]
    want, result = expected(harness.overrides, left, right)
    assert messages.stamp_ns(disp_msg.header) == messages.stamp_ns(gcp_msg.header) == 5_000_000_123
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
        wait_for(lambda: harness.newest_stamp() == stamp, encoding)
    for alpha_encoding in ('rgba8', 'bgra8'):  # 4-channel: built by hand, alpha must be ignored
        stamp += 1_000_000
        for side, img in (('left', left), ('right', right)):
            order = img if alpha_encoding == 'rgba8' else img[:, :, ::-1]
            rgba = np.dstack([order, np.full(img.shape[:2], 7, np.uint8)])
            harness.send(side, None, None, stamp, {
                'height': img.shape[0], 'width': img.shape[1], 'encoding': alpha_encoding,
                'step': img.shape[1] * 4, 'is_bigendian': 0, 'data': rgba.tobytes()})
        wait_for(lambda: harness.newest_stamp() == stamp, alpha_encoding)
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
        return [messages.stamp_ns(m.header) for m in harness.disparity]

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
    assert harness.node.stats.totals().stale == 0


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
        ({'precision': 'fp16'},
         "precision must be one of 'auto', 'int8', 'bf16', 'fp32', got 'fp16'"),
        ({'precision': True}, "expected 'Type.STRING' got 'Type.BOOL'"),  # rclpy's own check
        ({'precision': 8}, "expected 'Type.STRING' got 'Type.INTEGER'"),
        ({'downsample': 3}, 'downsample'),
        ({'device': 'cuda:7'}, "device 'cuda:7'"),
    ]:
        (result,) = harness.set_params(values)[:1]
        assert not result.successful and reason in result.reason, (values, result.reason)
    assert harness.node.get_parameter('census.theta').value == 0.6
    for precision in ('bf16', 'auto', 'fp32'):
        assert all(r.successful for r in harness.set_params({'precision': precision}))
        assert harness.node.pipeline.config.precision == precision
    harness.send_pair(left, right, 'rgb8', 7_000_000_000)
    wait_for(lambda: harness.disparity, 'disparity after set')
    overrides = {**harness.overrides, 'census.theta': 0.6, 'census.P1': 6.0,
                 'census.P2': 100.0, 'paths': 8, 'precision': 'fp32', 'downsample': 2}
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
    wait_for(lambda: harness.newest_stamp() == 8_000_000_000,
             'disparity after cost switch')
    want, _ = expected({**overrides, 'cost': 'sad', 'sad.P2': 20.0}, left, right)
    np.testing.assert_array_equal(image_to_array(harness.disparity[-1].image), want)

    # Values that cross (as `ros2 param load` sets P1 before P2) are taken and wait.
    assert all(r.successful for r in harness.set_params({'sad.P1': 30.0}))
    assert harness.node.pipeline.config.p1 == 0.02  # the last consistent values
    assert harness.node.params.pending == ['sad: P2 (20.0) must be >= P1 (30.0)']
    assert any('waiting for that, the node keeps its last consistent values' in m
               for m in harness.error_logs('WARN'))
    assert harness.node.get_parameter('sad.P1').value == 30.0
    assert all(r.successful for r in harness.set_params({'sad.P2': 40.0}))
    config = harness.node.pipeline.config
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
