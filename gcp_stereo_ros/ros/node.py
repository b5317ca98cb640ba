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

Start-up settings that cannot work (invalid values, a missing weights file, `device: cuda`
without a GPU, an unreadable params file) end the process with one line and exit code 2;
unknown parameter names are reported as warnings. Ctrl-C or SIGTERM stops a frame in
progress between two rows of a kernel or two CNN layers, so the process exits promptly.
"""
import array
import gc
import math
import os
import signal
import sys
import time
import traceback

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import Image, RegionOfInterest
from stereo_msgs.msg import DisparityImage

from . import messages
from .live_params import LiveParameters
from .params import BY_NAME, check_params_files, describe_unknown, NODE_NAME
from .rosimage import image_to_array
from .stereo_input import StereoInput
from .worker import NewestWorker
from ..stereo.cancel import CancelFlag, Cancelled
from ..stereo.images import mask_image
from ..stereo.pipeline import mmap_large_arrays

LOG_PERIOD = 5.0  # seconds between two logs of the same text
STOP_SECONDS = 1.5  # shutdown waits this long for the frame in progress to stop


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
        self._last_log = {}  # text -> [monotonic time logged, repeats not logged since]
        self.processed = 0
        self.errors = 0
        self._cancel = CancelFlag()
        self.stopped = False  # set by destroy_node: the worker thread has ended
        try:  # raises for start-up values that cannot work (weights, device, ranges)
            self.params = LiveParameters(self, on_sync_change=lambda v: self.input.reset_sync(v))
        except Exception:
            super().destroy_node()
            raise
        self.input = StereoInput(self, self.params.values, on_pair=self._on_pair, log=self._log)
        self._pub_disp = self.create_publisher(DisparityImage, 'disparity', 5)
        self._pub_gcp = self.create_publisher(Image, 'gcp_mask', 5)
        self._pub_conf = self.create_publisher(Image, 'confidence', 5)
        self._window = {'start': time.monotonic(), 'received': 0, 'seconds': {}}
        unknown = [n for n in self._parameter_overrides if not self.has_parameter(n)]
        if unknown:
            self.get_logger().warn(f'ignoring unknown parameter(s) '
                                   f'{describe_unknown(unknown, BY_NAME)}')
        self._worker = NewestWorker(self._process, 'gcp_stereo_worker',
                                    on_error=self._on_worker_error, on_idle=self._on_idle)
        self.get_logger().info(f'ready: {self.params.pipeline.config}')

    @property
    def stats(self):
        """Images received, pairs processed, pairs dropped as stale, errors."""
        return {'received': self.input.received, 'processed': self.processed,
                'stale': self._worker.stale, 'errors': self.errors}

    def _on_pair(self, stamp, left_msg, right_msg):
        self._worker.put((stamp, left_msg, right_msg))

    def _log(self, severity, text, detail=''):
        """
        Log `text` ('error' or 'warn') at most once per LOG_PERIOD, with `detail` appended.

        Repeats of the same text in between are counted and the count is logged with the
        next one; `detail` (a stamp, say) is not part of what repeats.
        """
        if severity == 'error':
            self.errors += 1
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

    def _process(self, stamp, left_msg, right_msg):
        pipeline = self.params.pipeline
        topics = self.input.topics()
        try:
            left = image_to_array(left_msg, topics['left'])
            right = image_to_array(right_msg, topics['right'])
            geom = messages.geometry(self.input.info['left'], self.input.info['right'],
                                     left.shape[:2], pipeline.config.max_disp)
            result = pipeline(left, right, cancel=self._cancel)
        except Cancelled:
            return  # shutting down
        except Exception as err:  # bad input, camera_info, weights or memory: say why
            self._log('error', f'skipping pair {topics["left"]} + {topics["right"]}: {err}',
                      f'stamp {stamp} ns')
            return
        try:
            self._publish(left_msg.header, result, pipeline.config, geom)
        except Exception as err:
            if self.context.ok():
                self._log('error', f'cannot publish the outputs: {err}', f'stamp {stamp} ns')
            return  # else shutting down while this pair was in flight: nothing to send to
        self.processed += 1
        self._log_progress(result.seconds)

    def _on_worker_error(self, err):
        where = traceback.extract_tb(err.__traceback__)[-1]
        self._log('error', f'unexpected {type(err).__name__} in the worker thread, which goes '
                           f'on: {err} (at {where.filename}:{where.lineno})')

    def _on_idle(self):
        self.params.pipeline.release()

    def _publish(self, header, result, config, geom):
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
        self._cancel.set()
        self.stopped = self._worker.stop(STOP_SECONDS)
        if not self.stopped:
            self.get_logger().warn(f'the frame in progress did not stop within {STOP_SECONDS} s; '
                                   'exiting anyway')
        return super().destroy_node()


def _cannot_start(err):
    """Print why the node cannot start, in one line; return the exit status."""
    print(f'{NODE_NAME}: error: cannot start: ' + (' '.join(str(err).split()) or repr(err)),
          file=sys.stderr)
    return 2


def main(args=None):
    argv = sys.argv if args is None else args
    try:
        check_params_files(argv)  # rcl would say it with a traceback
        extra = remove_ros_args(argv)[1:]
    except Exception as err:  # rcl's own argument errors
        return _cannot_start(err)
    if extra and extra[0] in ('-h', '--help'):
        print(__doc__.strip())
        return 0
    if extra:  # ROS arguments go after --ros-args; anything else is a mistake
        print(f'{NODE_NAME}: error: unrecognized arguments: {" ".join(extra)} '
              '(parameters go after --ros-args, e.g. --ros-args -p max_disparity:=192)',
              file=sys.stderr)
        return 2
    node = None
    try:
        try:
            mmap_large_arrays()
            rclpy.init(args=argv)
            node = GcpStereoNode()
        except Exception as err:  # settings that cannot work: one line, no traceback
            return _cannot_start(err)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # Ctrl-C or shutdown, while starting or spinning
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):  # a second Ctrl-C must not abort the exit
            signal.signal(sig, signal.SIG_IGN)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if node is not None and not node.stopped:  # the interpreter's exit would abort on it
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    gc.freeze()  # else the interpreter's exit spends about 0.7 s of CPU collecting objects
    return 0
