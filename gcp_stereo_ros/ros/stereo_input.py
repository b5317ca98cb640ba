"""The node's input: left and right image and camera_info subscriptions, paired by stamp."""
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import qos_profile_sensor_data
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, Image

from .graph import shm_segment_bytes
from .messages import stamp_ns
from .params import make_sync
from .sync import other_side, SIDES

STREAK_WARN = 10  # one side arriving this often in a row without its twin -> warning
SHM_ADVICE = ('raise segment_size in the Fast DDS profile of every process of the graph '
              '(FASTRTPS_DEFAULT_PROFILES_FILE; config/fastdds.xml has 32 MiB, '
              'the default is 0.5 MiB)')


class StereoInput:
    """
    Subscribe `<side>/image_rect` and `<side>/camera_info` and pair images by stamp.

    Each pair goes to `on_pair(stamp_ns, left_msg, right_msg)`; the newest camera_info of
    each side is kept in `info`. Counts images in `received`. Warnings (a side without its
    twin, images lost in transport or announced larger than the shared-memory segment) go to
    `log(severity, text)`, which rate-limits them.
    """

    def __init__(self, node, values, on_pair, log):
        self._on_pair = on_pair
        self._log = log
        self.sync = make_sync(values)
        self.received = 0
        qos = {'qos_overriding_options': QoSOverridingOptions.with_default_policies()}
        self.subs = {side: node.create_subscription(
            Image, f'{side}/image_rect', lambda m, s=side: self._on_image(s, m),
            qos_profile_sensor_data, event_callbacks=SubscriptionEventCallbacks(
                message_lost=lambda _, s=side: self._on_lost(s)), **qos) for side in SIDES}
        self.info = dict.fromkeys(SIDES)
        self._info_subs = [node.create_subscription(
            CameraInfo, f'{side}/camera_info', lambda m, s=side: self._on_info(s, m),
            qos_profile_sensor_data, **qos) for side in SIDES]
        self._segment = shm_segment_bytes()

    def topics(self):
        """Return the resolved image topic names, by side."""
        return {side: sub.topic_name for side, sub in self.subs.items()}

    def reset_sync(self, values):
        """Start pairing afresh with the sync parameters in `values`."""
        self.sync = make_sync(values)

    def _on_image(self, side, msg):
        self.received += 1
        pair = self.sync.add(side, stamp_ns(msg.header), msg, len(msg.data))
        if self.sync.unmatched_streak(side) == STREAK_WARN:
            topics = self.topics()
            self._log('warn',
                      f'{topics[side]}: {STREAK_WARN} images in a row without a matching '
                      f'{topics[other_side(side)]} image. Check the stamps and the sync '
                      "parameters; with large best-effort images, Fast DDS's default 512 KB "
                      'shared-memory segment drops them: set FASTRTPS_DEFAULT_PROFILES_FILE '
                      "to this package's config/fastdds.xml.")
        if pair is not None:
            self._on_pair(*pair)

    def _on_info(self, side, msg):
        self.info[side] = msg
        if msg.width * msg.height > self._segment:  # even as mono8
            self._log('warn',
                      f'{self.topics()[side]}: its camera_info announces {msg.width}x'
                      f'{msg.height} images, {msg.width * msg.height / (1 << 20):.0f} MiB or '
                      f'more, larger than the {self._segment / (1 << 20):g} MiB shared-memory '
                      f'segment: Fast DDS will lose them on the way; {SHM_ADVICE}.')

    def _on_lost(self, side):
        self._log('warn',
                  f'{self.topics()[side]}: images lost in transport. Fast DDS drops images '
                  "larger than the publisher's shared-memory segment (here "
                  f'{self._segment / (1 << 20):g} MiB); if yours are, {SHM_ADVICE}.')
