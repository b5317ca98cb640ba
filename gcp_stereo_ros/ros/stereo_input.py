"""
The node's input: left and right image and camera_info subscriptions, paired by stamp.

While the worker is busy the executor does not take images at all: the middleware keeps
the newest one per side (history depth 1) and drops older ones, so input the node cannot
use costs it nothing but the middleware's own receiving. When the worker is idle again it
wakes the executor, which takes the newest images and pairs them.
"""
import os
import time

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import DurabilityPolicy, qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from .graph import shm_segment_bytes
from .messages import stamp_ns
from .sync import CameraInfos, image_sync, other_side, SIDES

STREAK_WARN = 10  # one side arriving this often in a row without its twin -> warning
SHM_ADVICE = ('raise segment_size in the Fast DDS profile of every process of the graph '
              '(FASTRTPS_DEFAULT_PROFILES_FILE; config/fastdds.xml has 32 MiB, '
              'the default is 0.5 MiB)')
# The sensor-data QoS (best effort, volatile), keeping only the newest image per side.
IMAGE_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT,
                       durability=DurabilityPolicy.VOLATILE)


def image_topic(side, values):
    """Return the image topic of `side` the parameters ask for (relative to the node)."""
    base = f'{side}/image_raw' if values['rectify'] else f'{side}/image_rect'
    return base + '/compressed' if values['image_transport'] == 'compressed' else base


class _WhileIdle(MutuallyExclusiveCallbackGroup):
    """Callbacks run one at a time, and only while `idle()`: else their messages wait."""

    def __init__(self, idle):
        super().__init__()
        self._idle = idle

    def can_execute(self, entity):
        return self._idle() and super().can_execute(entity)

    def beginning_execution(self, entity):
        return self._idle() and super().beginning_execution(entity)


class StereoInput:
    """
    Subscribe the images and `<side>/camera_info` and pair the images by stamp.

    Image topics follow the parameters (see `image_topic`). Each pair goes to
    `on_pair(stamp_ns, left_msg, right_msg, info)`, `info` {side: the camera_info of that
    image's stamp} (sync.CameraInfos; None per side before any camera_info came). Once the
    camera_info stamps are seen to follow the images' (or before the first camera_info
    with `rectify`), a pair whose camera_info has not come yet waits for it; if the next
    pair comes first, or a newer camera_info shows that its own never will, it goes with
    the newest (warned). Camera_info stamped otherwise (a calibration sent once, say) is
    used as it is, the newest.
    Images are taken only while `idle()`, and `wake()` has the executor look again. The
    newest camera_info of each side is `info`; `received` and `last_stamp` count and date
    the images taken, per side; `arrived` counts the images that arrived, taken or not:
    the publisher's sequence number says how many it sent since the last one taken (the
    middleware keeps only the newest while the node is busy). `paired_at` is the
    time.monotonic() of the last pair and `unpaired_since` that of the first image taken
    since then (None while the last image taken made a pair). Images lost in transport or
    announced (by camera_info) larger than the shared-memory segment are warned about
    through `log(severity, text)`, which rate-limits.
    """

    def __init__(self, node, values, on_pair, idle, log):
        self._node = node
        self._on_pair = on_pair
        self._log = log
        self._segment = shm_segment_bytes()
        self._group = _WhileIdle(idle)
        self._qos = {'qos_overriding_options': QoSOverridingOptions.with_default_policies()}
        self._wake = node.create_guard_condition(lambda: None)
        self.received = dict.fromkeys(SIDES, 0)
        self.arrived = dict.fromkeys(SIDES, 0)
        self.last_stamp = dict.fromkeys(SIDES)
        self.paired_at = None
        self.unpaired_since = None
        self._waiting = None  # a pair waiting for its camera_info
        self._stamped = False  # camera_info stamps have matched image stamps
        self._recent = []  # the stamps {side: ns} of the last pairs
        self._info_subs = [node.create_subscription(
            CameraInfo, f'{side}/camera_info', lambda m, s=side: self._on_info(s, m),
            qos_profile_sensor_data, **self._qos) for side in SIDES]
        self.subs = {}
        self.subscribe(values)

    def subscribe(self, values):
        """(Re)subscribe the image topics the parameters ask for; start pairing afresh."""
        for sub in self.subs.values():
            self._node.destroy_subscription(sub)
        self._rectify = values['rectify']
        self._sequence = dict.fromkeys(SIDES)  # the last taken image's publication number
        kind = CompressedImage if values['image_transport'] == 'compressed' else Image
        self.subs = {side: self._node.create_subscription(
            kind, image_topic(side, values), lambda m, i, s=side: self._on_image(s, m, i),
            IMAGE_QOS, callback_group=self._group, event_callbacks=SubscriptionEventCallbacks(
                message_lost=lambda _, s=side: self._on_lost(s)), **self._qos)
            for side in SIDES}
        self.reset_sync(values)

    def topics(self):
        """Return the resolved image topic names, by side."""
        return {side: sub.topic_name for side, sub in self.subs.items()}

    @property
    def info(self):
        """Return the newest camera_info of each side (None before the first)."""
        return self.infos.newest

    def reset_sync(self, values):
        """Start pairing afresh with the sync parameters in `values`."""
        self.sync = image_sync(values)
        newest = getattr(self, 'infos', None)
        self.infos = CameraInfos(self.sync.tolerance_ns)
        for side, msg in (newest.newest.items() if newest else ()):
            if msg is not None:
                self.infos.add(side, stamp_ns(msg.header), msg)
        self._release(force=True)

    def close(self):
        """Unsubscribe every topic and destroy the guard condition `wake` triggers."""
        for sub in (*self._info_subs, *self.subs.values()):
            self._node.destroy_subscription(sub)
        self._node.destroy_guard_condition(self._wake)

    def wake(self):
        """Have the executor look at the image subscriptions again (any thread)."""
        self._wake.trigger()

    def _on_image(self, side, msg, info):
        self.received[side] += 1
        sequence, last = info.get('publication_sequence_number'), self._sequence[side]
        counted = None not in (sequence, last) and sequence > last
        # the images sent since the last one taken; not known (and counted as 1 arrived) when
        # the middleware gives no numbers, or a new publisher numbers from 1 again
        sent = sequence - last if counted else None
        self.arrived[side] += sent or 1
        self._sequence[side] = sequence
        stamp = self.last_stamp[side] = stamp_ns(msg.header)
        pair = self.sync.add(side, stamp, msg, len(msg.data), sent)
        if self.sync.unmatched_streak(side) == STREAK_WARN:
            topics = self.topics()
            hint = ('' if os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE') else
                    "; with large best-effort images, Fast DDS's default 512 KB shared-memory "
                    'segment drops them: set FASTRTPS_DEFAULT_PROFILES_FILE to this '
                    "package's config/fastdds.xml")
            self._node.get_logger().warn(
                f'{topics[side]}: {STREAK_WARN} images in a row without a matching '
                f'{topics[other_side(side)]} image (newest stamps: {side} {stamp} ns, '
                f'{other_side(side)} {self.last_stamp[other_side(side)]} ns). Check the stamps '
                f'and the sync parameters{hint}.')
        if pair is not None:
            self.paired_at, self.unpaired_since = time.monotonic(), None
            self._release(force=True)
            self._waiting = pair
            self._release()
        elif self.unpaired_since is None:
            self.unpaired_since = time.monotonic()

    def _release(self, force=False):
        """Hand the waiting pair on once its camera_info is here (or `force`: anyway)."""
        if self._waiting is None:
            return
        stamps = {side: stamp_ns(msg.header) for side, msg in self._waiting.items()}
        if stamps not in self._recent:
            self._recent = self._recent[-9:] + [stamps]
        info = self.infos.match(stamps)
        wait = self._stamped or (self._rectify and not self.infos.seen())
        if info is None and (not wait or force or self.infos.passed(stamps)):
            if wait:
                self._log('warn', 'no camera_info stamped as the images (within the sync '
                          'tolerance) came before the next pair: using the newest ones',
                          f'stamp {stamps["left"]} ns')
            info = dict(self.infos.newest)
        if info is not None:
            pair, self._waiting = self._waiting, None
            self._on_pair(stamps['left'], pair['left'], pair['right'], info)

    def _on_info(self, side, msg):
        stamp = stamp_ns(msg.header)
        self.infos.add(side, stamp, msg)
        tolerance = self.infos.tolerance_ns
        self._stamped |= any(abs(s[side] - stamp) <= tolerance for s in self._recent)
        self._release()
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
                  f'{self._segment / (1 << 20):g} MiB), and images sent faster than it can '
                  f'hand them over; if yours are that large, {SHM_ADVICE}.')
