"""
The node's /diagnostics: one diagnostic_msgs/DiagnosticArray a second.

Published as diagnostic_updater does (it has no Python package on PyPI): one status named
'<node name>: stereo', its values as key/value strings, on the absolute topic
/diagnostics, once a second of steady time (so also under use_sim_time without a clock).
It reads the node's public parts only: its `NodeStats` (stats.py), its `StereoInput`'s
counters, its parameters and pipeline, and `busy`.
"""
from collections import deque
import math
import os
import time
from typing import NamedTuple

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType

from .cnn_setup import cnn_precision
from .stats import Totals, Trust

NO_PAIR_SECONDS = 5.0  # images arriving this long without a pair -> WARN


class Reading(NamedTuple):
    """The node's counters at `time` (time.monotonic(), s), as each published status read them."""

    time: float
    taken_left: int  # images taken (StereoInput.received)
    taken_right: int
    arrived_left: int  # images arrived, taken or not (StereoInput.arrived)
    arrived_right: int
    totals: Totals


class Diagnostics:
    """
    Publish the health of `node` (a GcpStereoNode) on /diagnostics once a second.

    Values: images arrived per second per side (StereoInput.arrived: while the worker is
    busy the node takes only the newest, and counts the others when it does), over the
    last NO_PAIR_SECONDS; pairs processed per second and latency from the images' stamp to
    publishing (mean and max) since the previous status, pairs dropped as stale, images
    dropped unmatched, errors, device, CNN precision (what precision 'auto' gave) and
    weights; and whether the depth can be trusted (stats.trust): the share of the valid
    window published and the disparity confidence over the last 5 pairs and their running
    levels, what the view check found in the newest pair, the misalignment and the cause.
    Level WARN while crossed parameter values wait (P1 > P2, c_low > c_hi), when images
    were taken for NO_PAIR_SECONDS and none of them paired (a frame that takes longer is no
    such case: the node takes no images meanwhile; the message says which topic is missing
    and why), when pairs were skipped since the previous status, or when the depth is not
    to be trusted (stats.trust: the cause named). (Weights that cannot be loaded stop the
    node at start-up and are refused when set.)
    """

    def __init__(self, node):
        self._node = node
        self._pub = node.create_publisher(DiagnosticArray, '/diagnostics', 1)
        self._readings = deque()  # the Readings of the statuses published
        self._timer = node.create_timer(1.0, self.publish,
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._start = self._reading(time.monotonic())  # before any status

    def close(self):
        """Stop publishing: destroy the publisher and the timer."""
        self._node.destroy_timer(self._timer)
        self._node.destroy_publisher(self._pub)

    def publish(self):
        """Publish the status of now and keep its reading for the next ones."""
        node = self._node
        now = time.monotonic()
        msg = DiagnosticArray(status=[self.status(now)])
        msg.header.stamp = node.get_clock().now().to_msg()
        self._pub.publish(msg)
        self._readings.append(self._reading(now))
        while len(self._readings) > 1 and now - self._readings[1].time >= NO_PAIR_SECONDS:
            self._readings.popleft()

    def _reading(self, now: float) -> Reading:
        inp = self._node.input
        return Reading(now, inp.received['left'], inp.received['right'], inp.arrived['left'],
                       inp.arrived['right'], self._node.stats.totals())

    def status(self, now: float | None = None) -> DiagnosticStatus:
        """
        Return the DiagnosticStatus at `now` (time.monotonic(), s; default: now).

        Reading it changes nothing: the rates and the latency compare the node's counters
        with those the published statuses read.
        """
        node, inp = self._node, self._node.input
        now = time.monotonic() if now is None else now
        current = self._reading(now)
        first = self._readings[0] if self._readings else self._start
        last = self._readings[-1] if self._readings else self._start
        seconds = max(now - first.time, 1e-9)
        rates = [(current.arrived_left - first.arrived_left) / seconds,
                 (current.arrived_right - first.arrived_right) / seconds,
                 (current.totals.processed - last.totals.processed) / max(now - last.time, 1e-9)]
        latency = [s.latency for s in node.stats.samples(since=last.time)
                   if s.latency is not None]
        totals, trust = current.totals, node.stats.trust()
        config = node.pipeline.config
        sync = inp.sync
        values = {
            'left images/s': f'{rates[0]:.1f}', 'right images/s': f'{rates[1]:.1f}',
            'pairs processed/s': f'{rates[2]:.2f}',
            'latency s (stamp to publish), mean': (
                f'{sum(latency) / len(latency):.3f}' if latency else ''),
            'latency s (stamp to publish), max': f'{max(latency):.3f}' if latency else '',
            'pairs processed': str(totals.processed), 'pairs dropped stale': str(totals.stale),
            'images dropped unmatched, left': str(sync.dropped['left']),
            'images dropped unmatched, right': str(sync.dropped['right']),
            'errors': str(totals.errors), 'device': config.device,
            'CNN descriptors': cnn_precision(config),
            'weights': config.weights or 'shipped with the package',
            **{f'{side} topic': topic for side, topic in inp.topics().items()},
            **trust_values(trust, totals.processed > 0),
        }
        busy = rates[2] or node.busy
        level, message = DiagnosticStatus.OK, 'processing' if busy else 'waiting for images'
        if node.params.pending:
            level = DiagnosticStatus.WARN
            message = ('; '.join(node.params.pending)
                       + ': parameters waiting, the last consistent ones are in use')
        elif (reason := self._no_pair(now, first, current)) is not None:
            level, message = DiagnosticStatus.WARN, reason
        elif totals.errors > last.totals.errors:
            level = DiagnosticStatus.WARN
            message = f'{totals.errors - last.totals.errors} pair(s) skipped: {totals.last_error}'
        elif trust.warning:
            level, message = DiagnosticStatus.WARN, trust.warning
        drift = node.drift.status()  # the misalignment's level (stereo/drift.py)
        if drift.level == 'ERROR' or (drift.level == 'WARN' and level == DiagnosticStatus.OK):
            level = getattr(DiagnosticStatus, drift.level)
            message = f'right view misaligned by {drift.message}'
        return DiagnosticStatus(
            level=level, name=f'{node.get_name()}: stereo', message=message, hardware_id='',
            values=[KeyValue(key=k, value=v) for k, v in values.items()])

    def _no_pair(self, now: float, first: Reading, current: Reading) -> str | None:
        """Say why no pair synced for NO_PAIR_SECONDS while images arrive; None otherwise."""
        inp = self._node.input
        window = now - first.time
        paired = now - (inp.paired_at or self._start.time)
        counts = {'left': current.taken_left - first.taken_left,
                  'right': current.taken_right - first.taken_right}
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


def trust_values(trust: Trust, any_pair: bool) -> dict[str, str]:
    """Return the status values of `trust` ('' each before the first pair)."""
    def fraction(value: float | None) -> str:
        return '' if value is None else f'{value:.3f}'
    misalignment = f'unknown ({trust.misalignment_note})' if any_pair else ''
    if trust.misalignment is not None:
        misalignment = f'{trust.misalignment:.2f}'
    return {
        'published share of valid window': fraction(trust.share),
        'published share of valid window, running level': fraction(trust.share_level),
        'disparity confidence mean': fraction(trust.confidence),
        'disparity confidence mean, running level': fraction(trust.confidence_level),
        'view check': '; '.join(f.text for f in trust.views) or ('ok' if any_pair else ''),
        'misalignment px': misalignment,
        'cause': trust.cause,
    }
