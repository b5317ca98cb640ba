"""
The node's /diagnostics: one diagnostic_msgs/DiagnosticArray a second.

Published as diagnostic_updater does (it has no Python package on PyPI): one status named
'<node name>: stereo', its values as key/value strings, on the absolute topic
/diagnostics, once a second of steady time (so also under use_sim_time without a clock).
"""
from collections import deque
import math
import os
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType

from .cnn_setup import cnn_precision

NO_PAIR_SECONDS = 5.0  # images arriving this long without a pair -> WARN


class Diagnostics:
    """
    Publish the health of `node` (a GcpStereoNode) on /diagnostics once a second.

    Values: images arrived per second per side (StereoInput.arrived: while the worker is
    busy the node takes only the newest, and counts the others when it does), over the
    last NO_PAIR_SECONDS; pairs processed per second, latency from the
    images' stamp to publishing (mean and max over the last second), pairs dropped as stale,
    images dropped unmatched, errors, device, CNN precision (what precision 'auto' gave) and
    weights. Level WARN while crossed parameter values wait (P1 > P2, c_low > c_hi), when
    images were taken for NO_PAIR_SECONDS and none of them paired (a frame that takes longer
    is no such case: the node takes no images meanwhile; the message says which topic
    is missing and why) or when pairs were skipped in the last second. (Weights that cannot
    be loaded stop the node at start-up and are refused when set.)
    """

    def __init__(self, node):
        self._node = node
        self._pub = node.create_publisher(DiagnosticArray, '/diagnostics', 1)
        self._started = time.monotonic()
        self._samples = deque()  # (time, images left, images right, processed, errors)
        self._timer = node.create_timer(1.0, self.publish,
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))

    def close(self):
        """Stop publishing: destroy the publisher and the timer."""
        self._node.destroy_timer(self._timer)
        self._node.destroy_publisher(self._pub)

    def publish(self):
        node = self._node
        msg = DiagnosticArray(status=[self.status()])
        msg.header.stamp = node.get_clock().now().to_msg()
        self._pub.publish(msg)

    def status(self):
        """Return the DiagnosticStatus of the last second (and of NO_PAIR_SECONDS for WARN)."""
        node, inp = self._node, self._node.input
        now = time.monotonic()
        sample = (now, inp.received['left'], inp.received['right'], node.processed, node.errors,
                  inp.arrived['left'], inp.arrived['right'])
        self._samples.append(sample)
        while len(self._samples) > 2 and now - self._samples[1][0] >= NO_PAIR_SECONDS:
            self._samples.popleft()
        first = self._samples[0] if len(self._samples) > 1 else (self._started,) + (0,) * 6
        last = self._samples[-2] if len(self._samples) > 1 else first
        seconds = max(now - first[0], 1e-9)
        rates = [(sample[i] - first[i]) / seconds for i in (5, 6)]
        rates.append((sample[3] - last[3]) / max(now - last[0], 1e-9))
        latency = node.take_latencies()
        config = node.pipeline.config
        sync = inp.sync
        values = {
            'left images/s': f'{rates[0]:.1f}', 'right images/s': f'{rates[1]:.1f}',
            'pairs processed/s': f'{rates[2]:.2f}',
            'latency s (stamp to publish), mean': (
                f'{sum(latency) / len(latency):.3f}' if latency else ''),
            'latency s (stamp to publish), max': f'{max(latency):.3f}' if latency else '',
            'pairs processed': str(node.processed), 'pairs dropped stale': str(node.stale),
            'images dropped unmatched, left': str(sync.dropped['left']),
            'images dropped unmatched, right': str(sync.dropped['right']),
            'errors': str(node.errors), 'device': config.device,
            'CNN descriptors': cnn_precision(config),
            'weights': config.weights or 'shipped with the package',
            **{f'{side} topic': topic for side, topic in inp.topics().items()},
        }
        busy = rates[2] or not node._worker.idle
        level, message = DiagnosticStatus.OK, 'processing' if busy else 'waiting for images'
        if node.params.pending:
            level = DiagnosticStatus.WARN
            message = ('; '.join(node.params.pending)
                       + ': parameters waiting, the last consistent ones are in use')
        elif (reason := self._no_pair(now)) is not None:
            level, message = DiagnosticStatus.WARN, reason
        elif sample[4] > last[4]:
            level = DiagnosticStatus.WARN
            message = f'{sample[4] - last[4]} pair(s) skipped: {node.last_error}'
        return DiagnosticStatus(
            level=level, name=f'{node.get_name()}: stereo', message=message, hardware_id='',
            values=[KeyValue(key=k, value=v) for k, v in values.items()])

    def _no_pair(self, now):
        """Say why no pair synced for NO_PAIR_SECONDS while images arrive; None otherwise."""
        inp = self._node.input
        first, sample = self._samples[0], self._samples[-1]
        window = now - first[0]
        paired = now - (inp.paired_at or self._started)
        counts = {'left': sample[1] - first[1], 'right': sample[2] - first[2]}
        if (inp.unpaired_since is None or now - inp.unpaired_since < NO_PAIR_SECONDS
                or window < NO_PAIR_SECONDS - 0.5 or not any(counts.values())):
            return None
        topics = inp.topics()
        head = f'no stereo pair for {paired:.0f} s: '
        for side, other in (('left', 'right'), ('right', 'left')):
            if not counts[side]:
                hint = ('' if os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE') else
                        "; large best-effort images need this package's Fast DDS profile "
                        '(FASTRTPS_DEFAULT_PROFILES_FILE=.../config/fastdds.xml) in every '
                        'process')
                return (f'{head}no image on {topics[side]} in {window:.0f} s while '
                        f'{topics[other]} gets {counts[other] / window:.1f}/s: check that it '
                        f'is published and remapped to this topic{hint}')
        left, right = inp.last_stamp['left'], inp.last_stamp['right']
        apart = f'{(left - right) / 1e9:+.3f} s apart'
        sync = inp.sync
        if sync.tolerance_ns == math.inf:
            fix = "one side's stamps went back in time, the other's did not (a camera reset?)"
        elif sync.tolerance_ns:
            fix = f'more than approximate_sync_tolerance_seconds ({sync.tolerance_ns / 1e9:g} s)'
        else:
            fix = ('set approximate_sync true (approximate_sync_tolerance_seconds 0: the '
                   'closest stamps), or fix the stamps')
        return (f'{head}{topics["left"]} and {topics["right"]} both arrive but their stamps '
                f'never match (newest: left {left} ns, right {right} ns, {apart}); {fix}')
