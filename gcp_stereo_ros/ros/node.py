"""gcp_stereo_node: disparity from synchronized rectified stereo images (CNN GCPs + SGM).

Follows stereo_image_proc's disparity node. Subscribes `left/image_rect`, `right/image_rect`
(mono8, mono16, rgb8, bgr8, rgba8, bgra8) and, when present, `left/camera_info`,
`right/camera_info`; publishes, stamped with the left header, `disparity`
(stereo_msgs/DisparityImage), `gcp_mask` (mono8, 255 = GCP) and `confidence` (32FC1 CNN
confidence, only while subscribed). Parameters (config/gcp_stereo.yaml) are live.

Start: `ros2 run gcp_stereo_ros gcp_stereo_node`, `gcp_stereo_node` or
`python -m gcp_stereo_ros.node`, each with the usual `--ros-args`.

Frames are processed in a worker thread, newest pair first: a pair still waiting when a
newer one completes is dropped and counted, so the node never falls behind and parameter
requests are served while a frame is being processed.
"""
import array
import sys
import threading
import time

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, Image, RegionOfInterest
from stereo_msgs.msg import DisparityImage

from . import messages
from ..stereo.cost import COSTS
from .params import BY_NAME, NODE_NAME, PARAMS, SYNC_PARAMS, config_from_params, cost_defaults, make_sync
from ..stereo.pipeline import StereoPipeline
from .rosimage import image_to_array
from .sync import SIDES, other_side
from ..stereo.images import mask_image

STREAK_WARN = 10  # one side arriving this often in a row without its twin -> warning
ERROR_PERIOD = 5.0  # seconds between two logs of the same error


class _Types:
    Image = Image
    RegionOfInterest = RegionOfInterest
    DisparityImage = DisparityImage


def _ros_data(buffer):
    """uint8 numpy -> array.array('B'): the one form rclpy takes without a per-byte check."""
    out = array.array('B')
    out.frombytes(buffer)
    return out


def _descriptor(param):
    desc = ParameterDescriptor(description=param.description)
    if param.range is not None:
        low, high, step = param.range
        if isinstance(param.default, int):
            desc.integer_range = [IntegerRange(from_value=low, to_value=high, step=step)]
        else:
            desc.floating_point_range = [FloatingPointRange(from_value=low, to_value=high, step=step)]
    return desc


class GcpStereoNode(Node):

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        # Cost-dependent parameters default to the chosen cost's values; overrides win.
        cost = self.declare_parameter('cost', BY_NAME['cost'].default, _descriptor(BY_NAME['cost'])).value
        defaults = cost_defaults(cost) if cost in COSTS else {}
        for p in (p for p in PARAMS if p.name != 'cost'):
            self.declare_parameter(p.name, defaults.get(p.name, p.default), _descriptor(p))
        self._values = {p.name: self.get_parameter(p.name).value for p in PARAMS}
        self._pipeline = StereoPipeline(self._config(self._values))
        self._sync = make_sync(self._values)
        self._candidate = None
        self.add_pre_set_parameters_callback(self._complete_cost_switch)
        self.add_on_set_parameters_callback(self._validate)
        self.add_post_set_parameters_callback(self._apply)

        qos = dict(qos_overriding_options=QoSOverridingOptions.with_default_policies())
        self._subs = {side: self.create_subscription(Image, f'{side}/image_rect',
                                                     lambda m, s=side: self._on_image(s, m),
                                                     qos_profile_sensor_data, **qos) for side in SIDES}
        self._info = dict.fromkeys(SIDES)
        self._info_subs = [self.create_subscription(CameraInfo, f'{side}/camera_info',
                                                    lambda m, s=side: self._info.__setitem__(s, m),
                                                    qos_profile_sensor_data, **qos) for side in SIDES]
        self._pub_disp = self.create_publisher(DisparityImage, 'disparity', 5)
        self._pub_gcp = self.create_publisher(Image, 'gcp_mask', 5)
        self._pub_conf = self.create_publisher(Image, 'confidence', 5)

        self._last_error = {}
        self.stats = dict(received=0, processed=0, stale=0, errors=0)
        self._window = dict(start=time.monotonic(), received=0, seconds={})
        self._pending = None
        self._stopping = False
        self._cv = threading.Condition()
        self._worker = threading.Thread(target=self._work, name='gcp_stereo_worker', daemon=True)
        self._worker.start()
        if self._pipeline.config.use_gcp:
            try:
                self._pipeline.net
            except Exception as err:  # keep serving: every pair will say why it is skipped
                self._error(f'CNN weights: {err}')
        self.get_logger().info(f'ready: {self._pipeline.config}')

    # ---- parameters -------------------------------------------------------------------
    @staticmethod
    def _config(values):
        return config_from_params({n: v for n, v in values.items() if BY_NAME[n].field})

    def _complete_cost_switch(self, params):
        """A cost switch brings that cost's theta, P1, P2, c_hi, c_low unless set alongside."""
        names = {p.name for p in params}
        for p in params:
            if p.name == 'cost' and p.value != self._values['cost'] and p.value in COSTS:
                params += [Parameter(n, value=v) for n, v in cost_defaults(p.value).items() if n not in names]
        return params

    def _validate(self, params):
        changes = {p.name: p.value for p in params if p.name in BY_NAME}  # not qos_overrides.*
        self._candidate = None
        if not changes:
            return SetParametersResult(successful=True)
        values = {**self._values, **changes}
        try:
            config = self._config(values)
            make_sync(values)
            pipeline = self._pipeline.with_config(config)
            if config.use_gcp:
                pipeline.net  # a missing or corrupt weights file is refused here, with its path
        except Exception as err:
            return SetParametersResult(successful=False, reason=str(err))
        self._candidate = (values, pipeline)
        return SetParametersResult(successful=True)

    def _apply(self, params):
        if self._candidate is None:
            return
        values, pipeline = self._candidate
        sync_changed = any(values[n] != self._values[n] for n in SYNC_PARAMS)
        self._values, self._pipeline = values, pipeline
        if sync_changed:
            self._sync = make_sync(values)
        self.get_logger().info('parameters: ' + ', '.join(f'{p.name}={p.value!r}' for p in params
                                                         if p.name in BY_NAME))

    # ---- input ------------------------------------------------------------------------
    def _on_image(self, side, msg):
        self.stats['received'] += 1
        self._window['received'] += 1
        pair = self._sync.add(side, messages.stamp_ns(msg.header), msg)
        if self._sync.unmatched_streak(side) == STREAK_WARN:
            other = other_side(side)
            self.get_logger().warn(
                f'{self._subs[side].topic_name}: {STREAK_WARN} images in a row without a matching '
                f'{self._subs[other].topic_name} image. Check the stamps and the sync parameters; '
                'with large best-effort images, Fast DDS\'s default 512 KB shared-memory segment drops '
                'them: set FASTRTPS_DEFAULT_PROFILES_FILE to this package\'s config/fastdds.xml.')
        if pair is not None:
            with self._cv:
                if self._pending is not None:
                    self.stats['stale'] += 1
                self._pending = pair
                self._cv.notify()

    def _error(self, text):
        """Log an error at most once per ERROR_PERIOD for the same text."""
        self.stats['errors'] += 1
        now = time.monotonic()
        if now - self._last_error.get(text, -ERROR_PERIOD) >= ERROR_PERIOD:
            self._last_error[text] = now
            self.get_logger().error(text)

    # ---- processing -------------------------------------------------------------------
    def _work(self):
        while True:
            with self._cv:
                while self._pending is None and not self._stopping:
                    self._cv.wait()
                if self._stopping:
                    return
                pair, self._pending = self._pending, None
            self._process(*pair)

    def _process(self, stamp, left_msg, right_msg):
        pipeline = self._pipeline
        topics = {side: self._subs[side].topic_name for side in SIDES}
        try:
            left = image_to_array(left_msg, topics['left'])
            right = image_to_array(right_msg, topics['right'])
            result = pipeline(left, right)
        except Exception as err:  # bad input or weights: say why, skip the pair, keep serving
            self._error(f'skipping pair {topics["left"]} + {topics["right"]} at stamp {stamp} ns: {err}')
            return
        try:
            self._publish(left_msg.header, result, pipeline.config)
        except Exception:
            if self.context.ok():
                raise
            return  # shutting down (Ctrl-C) while this pair was in flight: nothing to send to
        self.stats['processed'] += 1
        self._log_progress(result.seconds)

    def _publish(self, header, result, config):
        geom = messages.geometry(self._info['left'], self._info['right'])
        self._pub_disp.publish(messages.disparity_message(_Types, header, result.disparity, config, geom, _ros_data))
        if result.gcp is not None:
            self._pub_gcp.publish(messages.image_message(_Types, header, mask_image(result.gcp), 'mono8', _ros_data))
            if self._pub_conf.get_subscription_count() > 0:
                self._pub_conf.publish(messages.image_message(_Types, header, result.cof_c, '32FC1', _ros_data))

    def _log_progress(self, seconds):
        w = self._window
        for stage, s in seconds.items():
            w['seconds'][stage] = w['seconds'].get(stage, 0.0) + s
        n = self._values['log_every_n_frames']
        if n and self.stats['processed'] % n == 0:
            elapsed = time.monotonic() - w['start']
            stages = ', '.join(f'{k} {1000 * v / n:.0f}' for k, v in w['seconds'].items())
            self.get_logger().info(
                f'{self.stats["processed"]} pairs processed; last {n}: ms per stage {stages}; '
                f'input {w["received"] / 2 / elapsed:.1f} pairs/s; dropped stale {self.stats["stale"]}, '
                f'unmatched left {self._sync.dropped_left} right {self._sync.dropped_right}, '
                f'errors {self.stats["errors"]}')
            self._window = dict(start=time.monotonic(), received=0, seconds={})

    def destroy_node(self):
        with self._cv:
            self._stopping = True
            self._cv.notify()
        self._worker.join()
        return super().destroy_node()


def main(args=None):
    rclpy.init(args=args)
    try:
        node = GcpStereoNode()
    except Exception as err:  # invalid start-up parameters: one clear line, no traceback
        print(f'{NODE_NAME}: cannot start: {err}', file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
