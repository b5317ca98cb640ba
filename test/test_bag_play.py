"""gcp-stereo-bag play into live subscribers."""
import os
import signal
import subprocess
import sys

from bag_helpers import cli, Listener, read_bag, REPO, TYPESTORE, write_bag
from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.ros import messages
from gcp_stereo_ros.ros.rosimage import array_to_image_fields, image_to_array
from gcp_stereo_ros.tools import bag
from gcp_stereo_ros.tools.bag.files import IMAGE, stamped_header
import numpy as np


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
        assert ([messages.stamp_ns(m.header) for _, m in got]
                == [messages.stamp_ns(m.header) for m in want]), topic
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
