"""
gcp_stereo_node: disparity from synchronized rectified stereo images (CNN GCPs + SGM).

Follows stereo_image_proc's disparity node. Subscribes `left/image_rect`, `right/image_rect`
(mono8, mono16, rgb8, bgr8, rgba8, bgra8) and, when present, `left/camera_info`,
`right/camera_info`; publishes, stamped with the left header, `disparity`
(stereo_msgs/DisparityImage), `gcp_mask` (mono8, 255 = GCP) and `confidence` (32FC1 CNN
confidence, only while subscribed). Parameters (config/gcp_stereo.yaml) are live.

Start: `ros2 run gcp_stereo_ros gcp_stereo_node`, `gcp_stereo_node` or
`python -m gcp_stereo_ros.node`, each with the usual `--ros-args`.

The node is three parts: `LiveParameters` (declare, validate, apply), `StereoInput`
(subscriptions and pairing) and a `NewestWorker` thread that processes the newest pair
and publishes here, so parameter requests are served while a frame is being processed.
"""
import array
import sys
import time

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import Image, RegionOfInterest
from stereo_msgs.msg import DisparityImage

from . import messages
from .live_params import LiveParameters
from .params import NODE_NAME
from .rosimage import image_to_array
from .stereo_input import StereoInput
from .worker import NewestWorker
from ..stereo.images import mask_image

ERROR_PERIOD = 5.0  # seconds between two logs of the same error


class _Types:
    Image = Image
    RegionOfInterest = RegionOfInterest
    DisparityImage = DisparityImage


def _ros_data(buffer):
    """Wrap uint8 numpy data as array.array('B'), the one form rclpy takes unchecked."""
    out = array.array('B')
    out.frombytes(buffer)
    return out


class GcpStereoNode(Node):

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        self.params = LiveParameters(self, on_sync_change=lambda v: self.input.reset_sync(v))
        self.input = StereoInput(self, self.params.values, on_pair=self._on_pair)
        self._pub_disp = self.create_publisher(DisparityImage, 'disparity', 5)
        self._pub_gcp = self.create_publisher(Image, 'gcp_mask', 5)
        self._pub_conf = self.create_publisher(Image, 'confidence', 5)
        self._last_error = {}
        self.processed = 0
        self.errors = 0
        self._window = {'start': time.monotonic(), 'received': 0, 'seconds': {}}
        self._worker = NewestWorker(self._process, name='gcp_stereo_worker')
        pipeline = self.params.pipeline
        if pipeline.config.use_gcp:
            try:
                pipeline.net
            except Exception as err:  # keep serving: every pair will say why
                self._error(f'CNN weights: {err}')
        self.get_logger().info(f'ready: {pipeline.config}')

    @property
    def stats(self):
        """Images received, pairs processed, pairs dropped as stale, errors."""
        return {'received': self.input.received, 'processed': self.processed,
                'stale': self._worker.stale, 'errors': self.errors}

    def _on_pair(self, stamp, left_msg, right_msg):
        self._worker.put((stamp, left_msg, right_msg))

    def _error(self, text):
        """Log an error at most once per ERROR_PERIOD for the same text."""
        self.errors += 1
        now = time.monotonic()
        if now - self._last_error.get(text, -ERROR_PERIOD) >= ERROR_PERIOD:
            self._last_error[text] = now
            self.get_logger().error(text)

    def _process(self, stamp, left_msg, right_msg):
        pipeline = self.params.pipeline
        topics = self.input.topics()
        try:
            left = image_to_array(left_msg, topics['left'])
            right = image_to_array(right_msg, topics['right'])
            result = pipeline(left, right)
        except Exception as err:  # bad input or weights: say why, keep serving
            self._error(f'skipping pair {topics["left"]} + {topics["right"]} '
                        f'at stamp {stamp} ns: {err}')
            return
        try:
            self._publish(left_msg.header, result, pipeline.config)
        except Exception:
            if self.context.ok():
                raise
            return  # shutting down (Ctrl-C) while this pair was in flight: nothing to send to
        self.processed += 1
        self._log_progress(result.seconds)

    def _publish(self, header, result, config):
        geom = messages.geometry(self.input.info['left'], self.input.info['right'])
        self._pub_disp.publish(messages.disparity_message(
            _Types, header, result.disparity, config, geom, _ros_data))
        if result.gcp is not None:
            self._pub_gcp.publish(messages.image_message(
                _Types, header, mask_image(result.gcp), 'mono8', _ros_data))
            if self._pub_conf.get_subscription_count() > 0:
                self._pub_conf.publish(messages.image_message(
                    _Types, header, result.cof_c, '32FC1', _ros_data))

    def _log_progress(self, seconds):
        w = self._window
        for stage, s in seconds.items():
            w['seconds'][stage] = w['seconds'].get(stage, 0.0) + s
        n = self.params.values['log_every_n_frames']
        if n and self.processed % n == 0:
            elapsed = time.monotonic() - w['start']
            pairs_in = (self.input.received - w['received']) / 2 / elapsed
            stages = ', '.join(f'{k} {1000 * v / n:.0f}' for k, v in w['seconds'].items())
            sync = self.input.sync
            self.get_logger().info(
                f'{self.processed} pairs processed; last {n}: ms per stage {stages}; '
                f'input {pairs_in:.1f} pairs/s; dropped stale {self._worker.stale}, '
                f'unmatched left {sync.dropped_left} right {sync.dropped_right}, '
                f'errors {self.errors}')
            self._window = {'start': time.monotonic(), 'received': self.input.received,
                            'seconds': {}}

    def destroy_node(self):
        self._worker.stop()
        return super().destroy_node()


def main(args=None):
    extra = remove_ros_args(sys.argv if args is None else args)[1:]
    if extra and extra[0] in ('-h', '--help'):
        print(__doc__.strip())
        return 0
    if extra:  # ROS arguments go after --ros-args; anything else is a mistake
        print(f'{NODE_NAME}: error: unrecognized arguments: {" ".join(extra)} '
              '(parameters go after --ros-args, e.g. --ros-args -p max_disparity:=192)',
              file=sys.stderr)
        return 2
    rclpy.init(args=args)
    node = None
    try:
        try:
            node = GcpStereoNode()
        except Exception as err:  # invalid start-up parameters: one line, no traceback
            print(f'{NODE_NAME}: error: cannot start: {err}', file=sys.stderr)
            return 2
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # Ctrl-C or shutdown, while starting or spinning
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
