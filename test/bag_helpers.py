"""What the bag tests share: reading and writing bags, the CLI, a live listener."""
import os
from pathlib import Path
import subprocess
import sys
import time

from gcp_stereo_ros.ros.graph import Spinner
from gcp_stereo_ros.ros.rosimage import array_to_image_fields
from gcp_stereo_ros.tools.bag.files import IMAGE, stamped_header, STRING
import numpy as np
from ros_helpers import wait_for
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores


REPO = Path(__file__).resolve().parents[1]
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)  # read back independently of the module under test
PARAMS = {'max_disparity': 64}  # the node's defaults otherwise (census, GCPs, shipped weights)


def read_bag(path):
    """({topic: [(bag timestamp, message)]}, {topic: connection}) of a whole bag."""
    msgs = {}
    with Reader(path) as reader:
        conns = {c.topic: c for c in reader.connections}
        for conn, timestamp, raw in reader.messages():
            msgs.setdefault(conn.topic, []).append(
                (timestamp, TYPESTORE.deserialize_cdr(raw, conn.msgtype)))
    return msgs, conns


def cli(*args):
    """
    Run `python -m gcp_stereo_ros.tools.bag ARGS` as a user runs it.

    It runs in the test's ROS environment.
    """
    return subprocess.run(
        [sys.executable, '-m', 'gcp_stereo_ros.tools.bag', *map(str, args)],
        cwd=REPO, env=os.environ, capture_output=True, text=True, timeout=120)


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


def crop_msg(frame, side, stamp, encoding='rgb8', rows=120):
    image = getattr(frame, side)[200:200 + rows, 300:460]
    fields = array_to_image_fields(image, 'rgb8')
    return TYPESTORE.types[IMAGE](header=stamped_header(stamp, f'{side}_camera'),
                                  **{**fields, 'encoding': encoding})


class Listener:
    """A node recording (arrival time, message) per topic, spun in a thread."""

    def __init__(self, rclpy, name, topics):
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
        self.spinner = Spinner(self.node)

    def wait(self, condition, what, timeout):
        wait_for(condition, lambda: f'{what}: got {self.counts()}', timeout)

    def counts(self):
        return {topic: len(msgs) for topic, msgs in self.got.items()}

    def close(self):
        self.spinner.stop()
        self.node.destroy_node()
