"""
gcp_stereo_node: disparity, depth and points from a stereo pair (CNN GCPs + SGM).

Follows stereo_image_proc's disparity and point_cloud nodes. Subscribes `left/image_rect`,
`right/image_rect` (mono8, mono16, rgb8, bgr8, rgba8, bgra8; `<topic>/compressed` with
`image_transport: compressed`; `left/image_raw`, `right/image_raw` with `rectify: true`)
and `left/camera_info`, `right/camera_info`; publishes, stamped with the left header,
`disparity` (stereo_msgs/DisparityImage; invalid pixels min_disparity - 1, as
stereo_image_proc's), `gcp_mask` (mono8, 255 = GCP) and, only while subscribed,
`confidence` (32FC1 CNN confidence), `disparity_confidence` (32FC1 probability that the
published disparity is within 3 px; 0 where none is published), `depth` (32FC1 metres,
REP 118, NaN where invalid), `points2` (organized sensor_msgs/PointCloud2, NaN where
invalid) and `disparity_color` (bgr8, the disparity colour-mapped for image viewers), and
/diagnostics once a second. Each image is paired with the camera_info of its stamp.
Parameters (config/gcp_stereo.yaml) are live.

Start: `ros2 run gcp_stereo_ros gcp_stereo_node`, `gcp_stereo_node` or
`python -m gcp_stereo_ros.node`, each with the usual `--ros-args`.

The node holds the `StereoPipeline` of its parameters and three parts: `LiveParameters`
(declare, validate, apply), `StereoInput` (subscriptions and pairing) and a `NewestWorker`
thread that processes the newest pair and publishes here, so parameter requests are
served while a frame is being processed. It counts what it does in its `NodeStats`
(`stats`), which /diagnostics and the progress log read.

Start-up settings that cannot work (invalid values, unknown names, a missing weights file,
`device: cuda` without a GPU, an unreadable params file) end the process with one line and
exit code 2. Ctrl-C or SIGTERM stops a frame in progress between two rows of a kernel or
two CNN layers, so the process exits promptly.
"""
import math
import time
import traceback

from rclpy.node import Node
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import Image, PointCloud2
from stereo_msgs.msg import DisparityImage

from .camera import camera_model, depth_scale, Rectifier
from .cnn_setup import cnn_precision, config_warnings, load_cnn
from .diagnostics import Diagnostics
from .live_params import LiveParameters
from .messages import output_messages, OUTPUTS
from .params import INPUT_PARAMS, NODE_NAME, SYNC_PARAMS
from .process import run_node
from .rclpy_messages import ros_data, RosTypes
from .rosimage import message_to_array
from .stats import NodeStats, Sample
from .stereo_input import StereoInput
from .worker import NewestWorker
from ..stereo.cancel import CancelFlag, Cancelled
from ..stereo.drift import Monitor
from ..stereo.health import published, ViewCheck
from ..stereo.pipeline import StereoPipeline
from ..stereo.postprocess import valid_window

LOG_PERIOD = 5.0  # seconds between two logs of the same text
STOP_SECONDS = 1.5  # shutdown waits this long for the frame in progress to stop
# computed only while subscribed
ON_DEMAND = ('confidence', 'disparity_confidence', 'depth', 'points2', 'disparity_color')


class GcpStereoNode(Node):
    """
    The node: configured (parameters, pipeline), then active (worker, topics) when made.

    Its steps are a lifecycle node's: `configure`, `activate`, `deactivate`, `cleanup`.
    """

    params = None  # LiveParameters, while configured
    stats: NodeStats  # what the node did since configured: pairs, errors, trust
    pipeline = None  # the StereoPipeline of the parameters, while configured
    active = False  # the worker started, the topics subscribed and published
    stopped = True  # no worker thread runs
    _cancel = None  # the worker's CancelFlag, while active

    def __init__(self, **kwargs):
        # Every start-up value is declared, so LiveParameters sees (and refuses) unknown names.
        super().__init__(NODE_NAME, automatically_declare_parameters_from_overrides=True,
                         **kwargs)
        try:  # raises for start-up values that cannot work (names, ranges, weights, device)
            self.configure()
        except Exception:
            super().destroy_node()
            raise
        self.activate()

    def configure(self):
        """Declare and check the parameters, build the pipeline and load its CNN; may raise."""
        self._last_log = {}  # text -> [monotonic time logged, repeats not logged since]
        self.stats = NodeStats()
        self.params = LiveParameters(self, check=self._check, on_change=self._on_params)
        self.pipeline, self._checked = self._checked, None
        self._warn_config()

    def activate(self):
        """Start the worker, subscribe and publish."""
        self._cancel = CancelFlag()
        self.stopped = False  # set by destroy_node: the worker thread has ended
        self._worker = NewestWorker(self._process, 'gcp_stereo_worker',
                                    on_error=self._on_worker_error,
                                    on_idle=lambda: self.input.wake(),
                                    on_quiet=lambda: self.pipeline.release(),
                                    on_stale=self.stats.dropped_stale)
        self.input = StereoInput(self, self.params.values, on_pair=self._on_pair,
                                 idle=lambda: self._worker.idle, log=self._log)
        # As image_pipeline's publishers on Jazzy: reliable, depth 1, QoS overridable.
        qos = QoSOverridingOptions.with_default_policies()
        types = {'disparity': DisparityImage, 'gcp_mask': Image, 'confidence': Image,
                 'disparity_confidence': Image, 'depth': Image, 'points2': PointCloud2,
                 'disparity_color': Image}
        self._pubs = {name: self.create_publisher(types[name], name, 1,
                                                  qos_overriding_options=qos)
                      for name in OUTPUTS}
        self._rectifier = Rectifier()
        self._warned = set()
        self._views = ViewCheck()
        self.drift = Monitor()  # the right view's misalignment, on its cadence (alignment.md)
        self._logged = (time.monotonic(), 0, self.stats.totals())  # at the last progress log
        self.diagnostics = Diagnostics(self)
        self.active = True
        config = self.pipeline.config
        self.get_logger().info(f'ready: {config}; CNN descriptors: {cnn_precision(config)}')

    def deactivate(self):
        """Stop the frame in progress and the worker, unsubscribe and unpublish."""
        self._stop()
        self.input.close()
        for pub in self._pubs.values():
            self.destroy_publisher(pub)
        self.diagnostics.close()
        self.drift.close()
        self._cancel = None
        self.active = False

    def cleanup(self):
        """Stop serving parameter requests; let the pipeline, its CNN and its arrays go."""
        self.params.close()
        self.params = self.pipeline = self._checked = None

    @property
    def busy(self) -> bool:
        """Return True while a pair waits for the worker or is being processed."""
        return not self._worker.idle

    def _check(self, config):
        """
        Build the pipeline of `config` as `_checked`, its CNN loaded; raise if it cannot work.

        LiveParameters' check, of the start-up values and of each request; the pipeline
        built for a request keeps the current one's CNN and arrays where it can.
        """
        pipeline = (StereoPipeline(config) if self.pipeline is None
                    else self.pipeline.with_config(config))
        self._checked = load_cnn(pipeline)

    def _on_params(self, names):
        """Take the parameters of a request: its pipeline, unless values wait; its topics."""
        pipeline, self._checked = self._checked, None
        if self.params.pending:
            self.get_logger().warn('; '.join(self.params.pending) + ': waiting for that, the '
                                   'node keeps its last consistent values: '
                                   f'{self.pipeline.config}')
        else:
            self.pipeline = pipeline
        self._warn_config()
        values = self.params.values
        if not self.active:  # activate subscribes as the values say
            return
        if any(n in INPUT_PARAMS for n in names):
            self.input.subscribe(values)
        elif any(n in SYNC_PARAMS for n in names):
            self.input.reset_sync(values)

    def _warn_config(self):
        for text in config_warnings(self.pipeline):
            self.get_logger().warn(text)

    def _on_pair(self, stamp, left_msg, right_msg, info):
        self._worker.put((stamp, left_msg, right_msg, info))

    def _log(self, severity, text, detail=''):
        """
        Log `text` ('error' or 'warn') at most once per LOG_PERIOD, with `detail` appended.

        Repeats of the same text in between are counted and the count is logged with the
        next one; `detail` (a stamp, say) is not part of what repeats.
        """
        if severity == 'error':
            self.stats.error(text)
        now = time.monotonic()
        last = self._last_log.setdefault(text, [-math.inf, 0])
        if now - last[0] < LOG_PERIOD:
            last[1] += 1
            return
        notes = [detail] if detail else []
        if last[1]:
            notes.append(f'{last[1]} more like it in the last {now - last[0]:.0f} s')
        getattr(self.get_logger(), severity)(text + (f' ({"; ".join(notes)})' if notes else ''))
        self._last_log[text] = [now, 0]

    def _warn_once(self, text):
        if text not in self._warned:
            self._warned.add(text)
            self.get_logger().warn(text)

    def _process(self, stamp, left_msg, right_msg, info):
        pipeline = self.pipeline
        values = self.params.values
        topics = self.input.topics()
        try:
            left, right = (message_to_array(msg, topics[side])
                           for side, msg in (('left', left_msg), ('right', right_msg)))
            if values['rectify']:
                left, right = (self._rectifier(side, info[side], image, topics[side])
                               for side, image in (('left', left), ('right', right)))
            model, why = camera_model(info, left.shape, pipeline.config)
            align = self.drift.before(left, right, pipeline.config, values)
            result = pipeline(left, right, cancel=self._cancel, camera=depth_scale(model),
                              misalignment=align)
            self.drift.after(result.seconds.get('align', 0.0))
        except Cancelled:
            return  # shutting down
        except Exception as err:  # bad input or a pair over memory_limit_mb: say why
            self._log('error', f'skipping pair {topics["left"]} + {topics["right"]}: {err}',
                      f'stamp {stamp} ns')
            return
        try:
            self._publish(left_msg.header, result, pipeline.config, info, model, why, left,
                          topics, values)
        except Exception as err:
            if self.context.ok():
                self._log('error', f'cannot publish the outputs: {err}', f'stamp {stamp} ns')
            return  # else shutting down while this pair was in flight: nothing to send to
        now = self.get_clock().now().nanoseconds  # 0: use_sim_time and no /clock yet
        share, confidence = published(result.disparity, result.disparity_confidence,
                                      valid_window(pipeline.config, result.disparity.shape))
        drift = self.drift.status()
        self.stats.pair_done(Sample(time.monotonic(), (now - stamp) / 1e9 if now else None,
                                    share, confidence, self._views(left, right), drift.px,
                                    drift.message), result.seconds)
        self._log_progress()

    def _publish(self, header, result, config, info, model, why, left, topics, values):
        wanted = {'disparity', 'gcp_mask'} | {
            n for n in ON_DEMAND if self._pubs[n].get_subscription_count() > 0}
        if model is None:
            if None not in info.values():  # calibrated, but wrongly: say so while it lasts
                self._log('warn', f'camera_info ignored (no f, t, depth or points2): {why}')
            elif wanted & {'depth', 'points2'}:
                self._warn_once(f'no depth or points2: {why}')
        if not header.frame_id:
            self._warn_once(f'{topics["left"]}: empty frame_id; outputs carry it as they are')
        msgs = output_messages(RosTypes, header, wanted, result, config, model, left,
                               values['use_color'], not values['avoid_point_cloud_padding'],
                               ros_data)
        for name, msg in msgs.items():
            self._pubs[name].publish(msg)

    def _log_progress(self):
        """Every log_every_n_frames pairs, log the ms per stage and the input since the last."""
        totals = self.stats.totals()
        n = self.params.values['log_every_n_frames']
        if not n or totals.processed % n:
            return
        since, received_then, then = self._logged
        now, received = time.monotonic(), sum(self.input.received.values())
        pairs = max(totals.processed - then.processed, 1)
        stages = ', '.join(
            f'{k} {1000 * (v - then.stage_seconds.get(k, 0.0)) / pairs:.0f}'
            for k, v in totals.stage_seconds.items() if v != then.stage_seconds.get(k))
        sync = self.input.sync
        self.get_logger().info(
            f'{totals.processed} pairs processed; last {pairs}: ms per stage {stages}; '
            f'input taken {(received - received_then) / 2 / (now - since):.1f} pairs/s; '
            f'dropped stale {totals.stale}, unmatched left {sync.dropped["left"]} right '
            f'{sync.dropped["right"]}, errors {totals.errors}')
        self._logged = (now, received, totals)

    def _on_worker_error(self, err):
        where = traceback.extract_tb(err.__traceback__)[-1]
        self._log('error', f'unexpected {type(err).__name__} in the worker thread, which goes '
                           f'on: {err} (at {where.filename}:{where.lineno})')

    def _stop(self):
        """Stop the frame in progress and the worker thread, if started; say if it lingers."""
        if self._cancel is None:
            return
        self._cancel.set()
        self.stopped = self._worker.stop(STOP_SECONDS)
        if not self.stopped:
            self.get_logger().warn(f'the frame in progress did not stop within {STOP_SECONDS} s; '
                                   'exiting anyway')

    def destroy_node(self):
        self._stop()
        return super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(GcpStereoNode, __doc__, NODE_NAME, args)
