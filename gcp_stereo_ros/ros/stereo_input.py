"""The node's input: left and right image and camera_info subscriptions, paired by stamp."""
from rclpy.qos import qos_profile_sensor_data
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, Image

from .messages import stamp_ns
from .params import make_sync
from .sync import other_side, SIDES

STREAK_WARN = 10  # one side arriving this often in a row without its twin -> warning


class StereoInput:
    """
    Subscribe `<side>/image_rect` and `<side>/camera_info` and pair images by stamp.

    Each pair goes to `on_pair(stamp_ns, left_msg, right_msg)`; the newest camera_info of
    each side is kept in `info`. Counts images in `received`.
    """

    def __init__(self, node, values, on_pair):
        self._node = node
        self._on_pair = on_pair
        self.sync = make_sync(values)
        self.received = 0
        qos = {'qos_overriding_options': QoSOverridingOptions.with_default_policies()}
        self.subs = {side: node.create_subscription(
            Image, f'{side}/image_rect', lambda m, s=side: self._on_image(s, m),
            qos_profile_sensor_data, **qos) for side in SIDES}
        self.info = dict.fromkeys(SIDES)
        self._info_subs = [node.create_subscription(
            CameraInfo, f'{side}/camera_info', lambda m, s=side: self.info.__setitem__(s, m),
            qos_profile_sensor_data, **qos) for side in SIDES]

    def topics(self):
        """Return the resolved image topic names, by side."""
        return {side: sub.topic_name for side, sub in self.subs.items()}

    def reset_sync(self, values):
        """Start pairing afresh with the sync parameters in `values`."""
        self.sync = make_sync(values)

    def _on_image(self, side, msg):
        self.received += 1
        pair = self.sync.add(side, stamp_ns(msg.header), msg)
        if self.sync.unmatched_streak(side) == STREAK_WARN:
            topics = self.topics()
            self._node.get_logger().warn(
                f'{topics[side]}: {STREAK_WARN} images in a row without a matching '
                f'{topics[other_side(side)]} image. Check the stamps and the sync parameters; '
                "with large best-effort images, Fast DDS's default 512 KB shared-memory "
                'segment drops them: set FASTRTPS_DEFAULT_PROFILES_FILE to this '
                "package's config/fastdds.xml.")
        if pair is not None:
            self._on_pair(*pair)
