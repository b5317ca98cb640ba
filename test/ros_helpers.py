"""
What the ROS tests share: the node harness, waiting, camera_info of a rectified pair.

`conftest.py` makes the `harness` fixture of `Harness`.
"""
import itertools
import time

from gcp_stereo_ros.ros import messages
from gcp_stereo_ros.ros.graph import Spinner
from gcp_stereo_ros.ros.node import GcpStereoNode
from gcp_stereo_ros.ros.params import config_from_params
from gcp_stereo_ros.ros.rosimage import array_to_image_fields
from gcp_stereo_ros.stereo.pipeline import StereoPipeline
import numpy as np
from rcl_interfaces.msg import Log
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image
from stereo_msgs.msg import DisparityImage

MAX_DISP = 32


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
        self.spinner = Spinner(self.node, self.peer)
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
        msg = image_msg(array, encoding, stamp_ns, frame_id)
        for key, value in (changes or {}).items():
            setattr(msg, key, value)
        self.pub[side].publish(msg)

    def newest_stamp(self):
        """Return the stamp (ns) of the newest disparity received, None before the first."""
        return messages.stamp_ns(self.disparity[-1].header) if self.disparity else None

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
        self.publish(f'{side}/camera_info', stamped(CameraInfo(**fields), stamp_ns))
        wait_for(lambda: self.node.input.info[side] is not None
                 and messages.stamp_ns(self.node.input.info[side].header) == stamp_ns,
                 f'{side} camera_info')

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
        self.spinner.stop()
        self.node.destroy_node()
        self.peer.destroy_node()


def wait_for(condition, what, timeout=60.0):
    """Wait until condition(); past `timeout` fail, saying `what` (or what() if callable)."""
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() >= end:
            raise AssertionError(f'timed out waiting for {what() if callable(what) else what}')
        time.sleep(0.01)


def stamped(msg, stamp_ns, frame_id=''):
    """Return `msg` with its header's stamp `stamp_ns` (ns) and `frame_id`."""
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    msg.header.frame_id = frame_id
    return msg


def image_msg(array, encoding, stamp_ns, frame_id=''):
    """Return `array` as a stamped sensor_msgs/Image of `encoding` (None: no pixels)."""
    fields = array_to_image_fields(array, encoding) if array is not None else {}
    return stamped(Image(**{**fields, 'data': bytes(fields.get('data', b''))}), stamp_ns,
                   frame_id)


def expected(overrides, left, right):
    result = StereoPipeline(config_from_params(overrides))(left, right)
    disp = result.disparity.copy()
    disp[np.isnan(disp)] = -1
    return disp, result


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
