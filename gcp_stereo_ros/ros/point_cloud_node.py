"""
point_cloud_node: points2 and depth from any disparity, with stereo_image_proc's interface.

Subscribes `left/image_rect_color` (its colour; `left/image_rect_color/compressed` with
`image_transport: compressed`), `left/camera_info`, `right/camera_info` and `disparity`
(stereo_msgs/DisparityImage), matched by stamp as stereo_image_proc's point_cloud_node does;
publishes, only while subscribed, `points2` (organized sensor_msgs/PointCloud2, stamped with
the disparity's header, invalid points NaN) and `depth` (32FC1 metres, REP 118). Camera infos
without a projection (uncalibrated) give NaN everywhere, as stereo_image_proc's do, and say
so once. Parameters (read at start-up, as stereo_image_proc's): `approximate_sync`,
`approximate_sync_tolerance_seconds` (0: the closest stamps), `queue_size`, `use_color`,
`avoid_point_cloud_padding` (read with each set), `image_transport`; QoS overrides of every
topic (`qos_overrides./left/image_rect_color.subscription.reliability`, ...).

Start: `ros2 run gcp_stereo_ros point_cloud_node`, or with `gcp_stereo_node` in one launch.
"""
import math
import time

import numpy as np
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from stereo_msgs.msg import DisparityImage

from .camera import stereo_model
from .messages import stamp_ns
from .pointcloud import disparity_of, geometry_messages
from .process import run_node
from .rclpy_messages import ros_data, RosTypes
from .rosimage import message_to_array
from .sync import StampSync, tolerance_ns

NAME = 'point_cloud_node'
LOG_PERIOD = 30.0  # seconds between two logs of the same text (stereo_image_proc: 30 s)
INPUTS = ('left/image_rect_color', 'left/camera_info', 'right/camera_info', 'disparity')


class PointCloudNode(Node):

    stopped = True  # no thread of its own to wait for at exit

    def __init__(self, **kwargs):
        super().__init__(NAME, **kwargs)
        declare = self.declare_parameter
        transport = declare('image_transport', 'raw').value
        queue_size = declare('queue_size', 5).value
        approximate = declare('approximate_sync', False).value
        tolerance = declare('approximate_sync_tolerance_seconds', 0.0).value
        declare('avoid_point_cloud_padding', False)
        declare('use_color', True)
        if transport not in ('raw', 'compressed'):
            raise ValueError(f"image_transport must be 'raw' or 'compressed', got {transport!r}")
        self._sync = StampSync(INPUTS, queue_size, tolerance_ns(approximate, tolerance))
        self._last_log = {}
        qos = {'qos_overriding_options': QoSOverridingOptions.with_default_policies()}
        image = INPUTS[0] + ('/compressed' if transport == 'compressed' else '')
        kinds = {image: CompressedImage if transport == 'compressed' else Image,
                 INPUTS[1]: CameraInfo, INPUTS[2]: CameraInfo, INPUTS[3]: DisparityImage}
        self._subs = [self.create_subscription(
            kind, topic, lambda m, n=name: self._on_message(n, m), qos_profile_sensor_data, **qos)
            for name, (topic, kind) in zip(INPUTS, kinds.items())]
        self._pubs = {name: self.create_publisher(kind, name, 1, **qos)
                      for name, kind in (('points2', PointCloud2), ('depth', Image))}

    def _on_message(self, name, msg):
        inputs = self._sync.add(name, stamp_ns(msg.header), msg)
        wanted = {n for n, pub in self._pubs.items() if pub.get_subscription_count() > 0}
        if inputs is None or not wanted:
            return
        try:
            self._publish(wanted, *(inputs[n] for n in INPUTS))
        except ValueError as err:  # input that cannot work: say why, go on
            self._log('error', f'skipping a disparity: {err}')

    def _publish(self, wanted, image_msg, left_info, right_info, disparity_msg):
        shape = (disparity_msg.image.height, disparity_msg.image.width)
        try:
            model = stereo_model(left_info, right_info, shape, math.inf)
        except ValueError as err:
            model = None
            self._log('warn', f'points2 and depth are NaN: {err}')
        disparity = disparity_of(disparity_msg, model, self._subs[3].topic_name)
        color = None
        if self.get_parameter('use_color').value:
            try:
                color = message_to_array(image_msg, self._subs[0].topic_name)
                if color.shape[:2] != disparity.shape:
                    raise ValueError(f'{color.shape[1]}x{color.shape[0]} pixels, the disparity '
                                     f'{disparity.shape[1]}x{disparity.shape[0]}')
            except ValueError as err:  # as stereo_image_proc: points without colour (0)
                self._log('warn', f'could not fill the colour of points2: {err}')
                color = np.zeros(disparity.shape, np.uint8)
        padded = not self.get_parameter('avoid_point_cloud_padding').value
        msgs = geometry_messages(RosTypes, disparity_msg.header, wanted, disparity, model, color,
                                 padded, ros_data)
        for name, out in msgs.items():
            self._pubs[name].publish(out)

    def _log(self, severity, text):
        """Log `text` at most once per LOG_PERIOD."""
        now = time.monotonic()
        if now - self._last_log.get(text, -math.inf) >= LOG_PERIOD:
            self._last_log[text] = now
            getattr(self.get_logger(), severity)(text)


def main(args: list[str] | None = None) -> int:
    return run_node(PointCloudNode, __doc__, NAME, args)
