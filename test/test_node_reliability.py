"""The ROS 2 node's reliability: errors, memory, start-up and shutdown."""
import os
import re
import signal
import subprocess
import threading
import time

from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.ros import messages
from gcp_stereo_ros.ros.graph import executable, Spinner, start_node, stop
from gcp_stereo_ros.ros.node import GcpStereoNode
from gcp_stereo_ros.ros.worker import NewestWorker
from gcp_stereo_ros.tools.load import cpu_seconds
import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from ros_helpers import image_msg, rectified_infos, wait_for
from sensor_msgs.msg import Image
from stereo_msgs.msg import DisparityImage

NODE_SCRIPT = str(executable('gcp_stereo_node'))


def test_errors_are_rate_limited_by_reason(harness, pair):
    left, right = pair
    small = np.ascontiguousarray(right[:100])
    for i in range(12):  # 12 bad pairs at 20 Hz, one reason: one line
        harness.send('left', left, 'rgb8', 50_000_000_000 + i * 50_000_000)
        harness.send('right', small, 'rgb8', 50_000_000_000 + i * 50_000_000)
        time.sleep(0.05)
    wait_for(lambda: harness.node.stats.totals().errors >= 1 and not harness.node.busy,
             'the errors')
    time.sleep(0.5)
    assert harness.node.stats.totals().errors >= 6  # the node takes the newest pair when idle
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
    assert harness.newest_stamp() == 61_000_000_000


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
        wait_for(lambda: harness.newest_stamp() == stamp, reason)
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
    assert harness.node.pipeline.backend.kept  # kept for the next frame ...
    wait_for(lambda: not harness.node.pipeline.backend.kept, 'arrays let go', 5)


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
    spinner = Spinner(peer)

    def send(side, image, stamp_ns):
        pubs[side].publish(image_msg(image, 'rgb8', stamp_ns))
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
        spinner.stop()
        peer.destroy_node()
    assert code == 0 and seconds < 2.0, (code, seconds)
    # nothing of the stopped frame
    assert big not in [messages.stamp_ns(m.header) for m in disparity]


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
    got = [(messages.stamp_ns(m.header), m.t) for m in harness.disparity]
    # the first pair waited for its camera_info only once their stamps were seen to follow the
    # images'; it went uncalibrated (t = 0)
    assert got[1:] == [(2_000_000_000, pytest.approx(0.3)), (3_000_000_000, pytest.approx(0.2))]
    assert got[0][0] == 1_000_000_000
