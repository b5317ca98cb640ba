"""
gcp_stereo_node: disparity, depth and points from a stereo pair (CNN GCPs + SGM).

Follows stereo_image_proc's disparity and point_cloud nodes. Subscribes `left/image_rect`,
`right/image_rect` (mono8, mono16, rgb8, bgr8, rgba8, bgra8; `<topic>/compressed` with
`image_transport: compressed`; `left/image_raw`, `right/image_raw` with `rectify: true`)
and `left/camera_info`, `right/camera_info`; publishes, stamped with the left header,
`disparity` (stereo_msgs/DisparityImage), `gcp_mask` (mono8, 255 = GCP) and, only while
subscribed, `confidence` (32FC1 CNN confidence), `depth` (32FC1 metres, REP 118) and
`points2` (organized sensor_msgs/PointCloud2), and /diagnostics once a second.
Parameters (config/gcp_stereo.yaml) are live.

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
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import Image, PointCloud2, PointField, RegionOfInterest
from stereo_msgs.msg import DisparityImage

from .camera import Rectifier, stereo_model
from .diagnostics import Diagnostics
from .live_params import LiveParameters
from .messages import output_messages, OUTPUTS
from .params import INPUT_PARAMS, NODE_NAME, SYNC_PARAMS
from .rosimage import message_to_array
from .stereo_input import StereoInput
from .worker import NewestWorker

ERROR_PERIOD = 5.0  # seconds between two logs of the same error
ON_DEMAND = ('confidence', 'depth', 'points2')  # computed only while subscribed


class _Types:
    Image = Image
    RegionOfInterest = RegionOfInterest
    DisparityImage = DisparityImage
    PointCloud2 = PointCloud2
    PointField = PointField


def _ros_data(buffer):
    """Wrap uint8 numpy data as array.array('B'), the one form rclpy takes unchecked."""
    out = array.array('B')
    out.frombytes(buffer)
    return out


class GcpStereoNode(Node):

    def __init__(self, **kwargs):
        # Every start-up value is declared, so LiveParameters sees (and refuses) unknown names.
        super().__init__(NODE_NAME, automatically_declare_parameters_from_overrides=True,
                         **kwargs)
        self.params = LiveParameters(self, on_change=self._on_params)
        self._worker = NewestWorker(self._process, name='gcp_stereo_worker',
                                    on_idle=lambda: self.input.wake())
        self.input = StereoInput(self, self.params.values, on_pair=self._on_pair,
                                 idle=lambda: self._worker.idle)
        # As image_pipeline's publishers on Jazzy: reliable, depth 1, QoS overridable.
        qos = QoSOverridingOptions.with_default_policies()
        types = {'disparity': DisparityImage, 'gcp_mask': Image, 'confidence': Image,
                 'depth': Image, 'points2': PointCloud2}
        self._pubs = {name: self.create_publisher(types[name], name, 1,
                                                  qos_overriding_options=qos)
                      for name in OUTPUTS}
        self._rectifier = Rectifier()
        self._last_error = {}
        self._warned = set()
        self._latency = []
        self.processed = 0
        self.errors = 0
        self.last_error = ''
        self.weights_error = None
        self._window = {'start': time.monotonic(), 'received': 0, 'seconds': {}}
        pipeline = self.params.pipeline
        if pipeline.config.use_gcp:
            try:
                self._load_weights(pipeline)
            except Exception as err:  # keep serving: every pair and /diagnostics say why
                self._error(f'CNN weights: {err}')
        self.diagnostics = Diagnostics(self)
        self.get_logger().info(f'ready: {pipeline.config}')

    @property
    def stale(self):
        """Return the number of pairs dropped because a newer one came before processing."""
        return self._worker.stale

    @property
    def stats(self):
        """Images received, pairs processed, pairs dropped as stale, errors."""
        return {'received': sum(self.input.received.values()), 'processed': self.processed,
                'stale': self.stale, 'errors': self.errors}

    def take_latencies(self):
        """Return and forget the seconds from stamp to publish of the pairs since last call."""
        latency, self._latency = self._latency, []
        return latency

    def _on_params(self, names):
        values = self.params.values
        if any(n in INPUT_PARAMS for n in names):
            self.input.subscribe(values)
        elif any(n in SYNC_PARAMS for n in names):
            self.input.reset_sync(values)

    def _on_pair(self, stamp, left_msg, right_msg):
        self._worker.put((stamp, left_msg, right_msg))

    def _error(self, text):
        """Log an error at most once per ERROR_PERIOD for the same text."""
        self.errors += 1
        self.last_error = text
        now = time.monotonic()
        if now - self._last_error.get(text, -ERROR_PERIOD) >= ERROR_PERIOD:
            self._last_error[text] = now
            self.get_logger().error(text)

    def _warn_once(self, text):
        if text not in self._warned:
            self._warned.add(text)
            self.get_logger().warn(text)

    def _load_weights(self, pipeline):
        try:
            pipeline.net
        except Exception as err:
            self.weights_error = str(err)
            raise
        self.weights_error = None

    def _process(self, stamp, left_msg, right_msg):
        pipeline = self.params.pipeline
        values = self.params.values
        topics = self.input.topics()
        info = dict(self.input.info)
        try:
            if pipeline.config.use_gcp:
                self._load_weights(pipeline)
            left, right = (message_to_array(msg, topics[side])
                           for side, msg in (('left', left_msg), ('right', right_msg)))
            if values['rectify']:
                left, right = (self._rectifier(side, info[side], image, topics[side])
                               for side, image in (('left', left), ('right', right)))
            result = pipeline(left, right)
        except Exception as err:  # bad input or weights: say why, keep serving
            self._error(f'skipping pair {topics["left"]} + {topics["right"]} '
                        f'at stamp {stamp} ns: {err}')
            return
        try:
            self._publish(left_msg.header, result, pipeline.config, info, left, topics, values)
        except Exception:
            if self.context.ok():
                raise
            return  # shutting down (Ctrl-C) while this pair was in flight: nothing to send to
        self._latency.append((self.get_clock().now().nanoseconds - stamp) / 1e9)
        self.processed += 1
        self._log_progress(result.seconds)

    def _publish(self, header, result, config, info, left, topics, values):
        wanted = {'disparity', 'gcp_mask'} | {
            n for n in ON_DEMAND if self._pubs[n].get_subscription_count() > 0}
        try:
            model = stereo_model(info['left'], info['right'], left.shape)
        except ValueError as err:
            model = None
            if wanted & {'depth', 'points2'}:
                self._warn_once(f'no depth or points2: {err}')
        if not header.frame_id:
            self._warn_once(f'{topics["left"]}: empty frame_id; outputs carry it as they are')
        msgs = output_messages(_Types, header, wanted, result, config, model, left,
                               values['use_color'], not values['avoid_point_cloud_padding'],
                               _ros_data)
        for name, msg in msgs.items():
            self._pubs[name].publish(msg)

    def _log_progress(self, seconds):
        w = self._window
        for stage, s in seconds.items():
            w['seconds'][stage] = w['seconds'].get(stage, 0.0) + s
        n = self.params.values['log_every_n_frames']
        if n and self.processed % n == 0:
            elapsed = time.monotonic() - w['start']
            received = sum(self.input.received.values())
            pairs_in = (received - w['received']) / 2 / elapsed
            stages = ', '.join(f'{k} {1000 * v / n:.0f}' for k, v in w['seconds'].items())
            sync = self.input.sync
            self.get_logger().info(
                f'{self.processed} pairs processed; last {n}: ms per stage {stages}; '
                f'input taken {pairs_in:.1f} pairs/s; dropped stale {self.stale}, '
                f'unmatched left {sync.dropped_left} right {sync.dropped_right}, '
                f'errors {self.errors}')
            self._window = {'start': time.monotonic(), 'received': received, 'seconds': {}}

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
