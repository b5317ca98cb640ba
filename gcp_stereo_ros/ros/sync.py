"""
One message of each of several topics by header stamp, a ROS-free stand-in for message_filters.

Shared by the node (left and right images), point_cloud_node (its four inputs) and the
offline rosbag tools. Its policies are message_filters' as stereo_image_proc's nodes choose
them (`tolerance_ns`): ExactTime (identical stamps), ApproximateEpsilonTime (stamps at most
a tolerance apart) or, with approximate sync and a tolerance of 0, ApproximateTime (the
closest stamps), simplified (see `StampSync`).
"""
import bisect
from collections import deque
import math
from statistics import median_low

from .params import BY_NAME, SYNC_PARAMS
from ..stereo.memory import MIB

SIDES = ('left', 'right')
PERIOD_GAPS = 30  # the stamp gaps an unbounded tolerance takes the frame period from
QUEUE_SHARE = 4  # each side's queue of the node's images holds at most memory_limit_mb / 4


def tolerance_ns(approximate, tolerance_seconds):
    """
    Return StampSync's tolerance for stereo_image_proc's two sync parameters.

    Not approximate: 0 (identical stamps); approximate with a tolerance of 0: math.inf (the
    closest stamps, ApproximateTime); else the tolerance in nanoseconds.
    """
    if not 0 <= tolerance_seconds < math.inf:
        raise ValueError(f'the tolerance must be a finite number of seconds >= 0, '
                         f'got {tolerance_seconds!r}')
    if not approximate:
        return 0
    return round(tolerance_seconds * 1e9) if tolerance_seconds > 0 else math.inf


class StampSync:
    """
    Match one message of each of `names` by stamp (integer ns); stamps may arrive out of order.

    With a finite `tolerance_ns` (0: identical stamps) a message completes a set as soon as
    every other topic holds a message within it of its stamp, the closest one, the older one
    on a tie; so keep it below half the frame period. With math.inf (the closest stamps, as
    ApproximateTime) it is just under half the frame period, the median of the last
    PERIOD_GAPS gaps between consecutive stamps of a topic per message its publisher sent
    (the shortest of the topics'), so that a set does not span two frames where messages
    were lost or skipped; before a topic's second message, identical stamps only (`flush`
    takes a recording of one frame).
    Each topic queues at most `queue_size` unmatched messages and, beyond its newest one, at
    most `max_bytes` of them (None = no byte bound; `add` is told each message's size); the
    oldest stamp goes first.
    A set discards, per topic, every queued message stamped at or before its own: a newer
    set won, so they can never be used. A later arrival stamped at or before the last set
    is held aside (the newest one per topic): from some topics only it is a straggler,
    discarded at the next set; once every topic has sent one, the stream went back in time
    (a looped bag replaying its stamps, even a one-frame bag repeating one stamp; a camera
    reset): the queues are cleared and matching starts afresh with the held messages.

    Counters: `sets`; `dropped` {name: messages discarded unmatched}.
    """

    def __init__(self, names, queue_size=5, tolerance_ns=0, max_bytes=None):
        if isinstance(queue_size, bool) or not isinstance(queue_size, int) or queue_size < 1:
            raise ValueError(f'queue_size must be an integer >= 1, got {queue_size!r}')
        if not tolerance_ns >= 0:
            raise ValueError(f'tolerance_ns must be >= 0, got {tolerance_ns!r}')
        if max_bytes is not None and not (isinstance(max_bytes, int) and max_bytes > 0):
            raise ValueError(f'max_bytes must be None or an integer > 0, got {max_bytes!r}')
        self.names = tuple(names)
        self.queue_size = queue_size
        self.tolerance_ns = tolerance_ns
        self.max_bytes = max_bytes
        self.sets = 0
        self.dropped = dict.fromkeys(self.names, 0)
        self._stamps = {name: [] for name in self.names}  # ascending, parallel to _msgs
        self._msgs = {name: [] for name in self.names}
        self._sizes = {name: [] for name in self.names}  # bytes of each queued message
        self._last = dict.fromkeys(self.names)  # the stamps of the last set
        self._back = dict.fromkeys(self.names)  # (stamp, msg, size) at or before _last
        self._streak = dict.fromkeys(self.names, 0)
        self._previous = dict.fromkeys(self.names)  # the stamp each topic added last
        # per topic, the gaps between its consecutive stamps per message sent, > 0
        self._gaps = {name: deque(maxlen=PERIOD_GAPS) for name in self.names}

    def add(self, name, stamp_ns, msg, size=0, sent=1):
        """
        Queue `msg` (of `size` bytes) of topic `name`; return {name: message} of a set.

        Return None while the set is incomplete. `sent`: the messages its publisher sent
        since the last one added, this one included (more where a subscriber keeps only the
        newest; None: not known, then its gap does not count), for the frame period.
        """
        self._check(name)
        previous, self._previous[name] = self._previous[name], stamp_ns
        gap = (stamp_ns - previous) // sent if previous is not None and sent else 0
        if gap > 0:
            self._gaps[name].append(gap)
        if self._last[name] is None or stamp_ns > self._last[name]:
            return self._add(name, stamp_ns, msg, size)
        if self._back[name] is not None:
            self._drop(name, 1)
        self._back[name] = stamp_ns, msg, size
        if None in self._back.values():
            return None
        back = self._back  # every topic went back: a new stream
        self._back = dict.fromkeys(self.names)
        self._last = dict.fromkeys(self.names)
        for other in self.names:
            self._discard_first(other, len(self._stamps[other]))
        for other in self.names:
            if other != name:
                self._add(other, *back[other])
        return self._add(name, *back[name])

    def unmatched_streak(self, name):
        """
        Return the number of messages of `name` discarded unmatched since the last set.

        Growth means its twins go missing.
        """
        self._check(name)
        return self._streak[name]

    def _add(self, name, stamp_ns, msg, size):
        picks, tolerance = {}, self._tolerance()
        for other in self.names:
            if other == name:
                continue
            stamps = self._stamps[other]
            lo = bisect.bisect_left(stamps, stamp_ns - tolerance)
            hi = bisect.bisect_right(stamps, stamp_ns + tolerance)
            if lo == hi:
                self._queue(name, stamp_ns, msg, size)
                return None
            picks[other] = _closest(stamps, lo, hi, stamp_ns)
        return self._take(picks, {name: msg}, {name: stamp_ns})

    def flush(self):
        """
        Return a set of the closest queued stamps while no frame period is known, else None.

        At the end of a recording, where an unbounded tolerance had nothing to go by: a
        recording of one frame from cameras with offset stamps.
        """
        queues = self._stamps
        if self.tolerance_ns < math.inf or any(self._gaps.values()) or not all(queues.values()):
            return None
        stamp = queues[self.names[0]][-1]
        return self._take({other: _closest(stamps, 0, len(stamps), stamp)
                           for other, stamps in queues.items()}, {}, {})

    def _tolerance(self):
        """
        Return the stamp difference a set may span, in ns.

        `tolerance_ns`, or for an unbounded one less than half the frame period: of the
        topics with one, the shortest median of their last PERIOD_GAPS gaps (0 before any).
        """
        if self.tolerance_ns < math.inf:
            return self.tolerance_ns
        periods = [median_low(gaps) for gaps in self._gaps.values() if gaps]
        return (min(periods) - 1) // 2 if periods else 0

    def _take(self, picks, out, last):
        """
        Return the set of the queued messages `picks` {name: index} and `out` {name: msg}.

        `out` and `last` {name: stamp} hold the message just added, if it is in the set.
        """
        for other, j in picks.items():
            last[other] = self._stamps[other].pop(j)
            out[other] = self._msgs[other].pop(j)
            del self._sizes[other][j]
        for other in self.names:
            self._discard_first(other, bisect.bisect_right(self._stamps[other], last[other]))
            if self._back[other] is not None:  # a straggler
                self._back[other] = None
                self._drop(other, 1)
        self._last = last
        self._streak = dict.fromkeys(self.names, 0)
        self.sets += 1
        return {other: out[other] for other in self.names}

    def _queue(self, name, stamp_ns, msg, size):
        i = bisect.bisect_right(self._stamps[name], stamp_ns)
        self._stamps[name].insert(i, stamp_ns)
        self._msgs[name].insert(i, msg)
        self._sizes[name].insert(i, size)
        while len(self._stamps[name]) > 1 and (
                len(self._stamps[name]) > self.queue_size
                or (self.max_bytes is not None and sum(self._sizes[name]) > self.max_bytes)):
            self._discard_first(name, 1)

    def _discard_first(self, name, n):
        for queue in (self._stamps, self._msgs, self._sizes):
            del queue[name][:n]
        self._drop(name, n)

    def _drop(self, name, n):
        self._streak[name] += n
        self.dropped[name] += n

    def _check(self, name):
        if name not in self.names:
            raise ValueError(f'no topic {name!r}; the topics: {", ".join(map(repr, self.names))}')


def _closest(stamps, lo, hi, stamp_ns):
    """Return the index in [lo, hi) of the stamp closest to `stamp_ns`, the older on a tie."""
    return min(range(lo, hi), key=lambda k: abs(stamps[k] - stamp_ns))


def image_sync(values):
    """Return the StampSync of the node's images for its parameter `values` (or defaults)."""
    queue_size, approximate, tolerance, memory_limit_mb = (
        values.get(name, BY_NAME[name].default) for name in SYNC_PARAMS)
    return StampSync(SIDES, queue_size, tolerance_ns(approximate, tolerance),
                     memory_limit_mb * MIB // QUEUE_SHARE)


def other_side(side):
    if side not in SIDES:
        raise ValueError(f"side must be 'left' or 'right', got {side!r}")
    return 'right' if side == 'left' else 'left'


class CameraInfos:
    """
    The recent camera_info messages of each side, by stamp, to pair each image with its own.

    As image_transport's camera subscribers do: an image goes with the camera_info of its
    stamp (within `tolerance_ns`, the pairs' StampSync's; identical stamps, as a camera
    driver gives its image and camera_info, where that is unbounded), whichever of the two
    was received first. `keep` messages per side are kept (the newest stamps).
    """

    def __init__(self, tolerance_ns=0, keep=30):
        self.tolerance_ns = tolerance_ns if tolerance_ns < math.inf else 0
        self.keep = keep
        self._by_stamp = {side: {} for side in SIDES}
        self.newest = dict.fromkeys(SIDES)  # the newest camera_info received, per side

    def add(self, side, stamp_ns, msg):
        infos = self._by_stamp[side]
        infos[stamp_ns] = msg
        while len(infos) > self.keep:
            del infos[min(infos)]
        self.newest[side] = msg

    def seen(self):
        """Return True once both sides have sent a camera_info."""
        return None not in self.newest.values()

    def match(self, stamps):
        """
        Return {side: the camera_info of its stamp in `stamps` ({side: ns})}, or None.

        None while a side has none within the tolerance yet.
        """
        out = {}
        for side, stamp in stamps.items():
            near = [s for s in self._by_stamp[side] if abs(s - stamp) <= self.tolerance_ns]
            if not near:
                return None
            out[side] = self._by_stamp[side][min(near, key=lambda s: abs(s - stamp))]
        return out

    def passed(self, stamps):
        """Return True if a side's newest camera_info is stamped after its `stamps` entry."""
        return any(self._by_stamp[side] and max(self._by_stamp[side]) > stamp + self.tolerance_ns
                   for side, stamp in stamps.items())
