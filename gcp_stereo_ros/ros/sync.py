"""
Left/right stereo pairing by header stamp, a ROS-free stand-in for message_filters.

Shared by the node and the offline rosbag tools. For two inputs it behaves like
message_filters' ExactTime policy (approximate=False: identical stamps) or a simplified
ApproximateTime policy (approximate=True: stamps at most `tolerance` seconds apart).
"""
import bisect
import math

SIDES = ('left', 'right')


class PairSync:
    """
    Pair left and right messages by stamp; stamps may arrive out of order.

    A message is paired as soon as the other side holds a message within tolerance (the
    closest one, the older one on a tie), so keep `tolerance` below half the frame period.
    Each side queues at most `queue_size` unpaired messages and, beyond its newest one, at
    most `max_bytes` of them (None = no byte bound; `add` is told each message's size); the
    oldest stamp goes first.
    Emitting a pair discards, per side, every queued message stamped at or before the
    paired one: a newer pair won, so they can never be used. A later arrival stamped at or
    before the last pair is held aside (the newest one per side): from one side alone it is
    a straggler, discarded at the next pair; once both sides have sent one, the stream went
    back in time (a looped bag replaying its stamps, even a one-frame bag repeating one
    stamp; a camera reset): the queues are cleared and pairing starts afresh with the two
    held messages. `tolerance` is ignored when exact.

    Counters: `pairs`, `dropped_left`, `dropped_right` (messages discarded unpaired).
    """

    def __init__(self, queue_size=10, approximate=False, tolerance=0.0, max_bytes=None):
        if isinstance(queue_size, bool) or not isinstance(queue_size, int) or queue_size < 1:
            raise ValueError(f'queue_size must be an integer >= 1, got {queue_size!r}')
        if not 0 <= tolerance < math.inf:
            raise ValueError(
                f'tolerance must be a finite number of seconds >= 0, got {tolerance!r}')
        if max_bytes is not None and not (isinstance(max_bytes, int) and max_bytes > 0):
            raise ValueError(f'max_bytes must be None or an integer > 0, got {max_bytes!r}')
        self.queue_size = queue_size
        self.max_bytes = max_bytes
        self.tolerance_ns = round(tolerance * 1e9) if approximate else 0
        self.pairs = 0
        self.dropped_left = 0
        self.dropped_right = 0
        self._stamps = {side: [] for side in SIDES}  # ascending stamps, parallel to _msgs
        self._msgs = {side: [] for side in SIDES}
        self._sizes = {side: [] for side in SIDES}  # bytes of each queued message
        self._last = {side: None for side in SIDES}  # stamps of the last emitted pair
        self._back = {side: None for side in SIDES}  # (stamp, msg, size) at or before _last
        self._streak = {side: 0 for side in SIDES}

    def add(self, side, stamp_ns, msg, size=0):
        """
        Queue `msg` (of `size` bytes) of `side`; return (stamp_left_ns, left_msg, right_msg).

        Return None while it waits for its twin.
        """
        other = other_side(side)
        if self._last[side] is None or stamp_ns > self._last[side]:
            return self._add(side, other, stamp_ns, msg, size)
        if self._back[side] is not None:
            self._drop(side, 1)
        self._back[side] = stamp_ns, msg, size
        if self._back[other] is None:
            return None
        back = self._back  # both sides went back: a new stream
        self._back = {s: None for s in SIDES}
        self._last = {s: None for s in SIDES}
        for s in SIDES:
            self._discard_upto(s, math.inf)
        self._add(other, side, *back[other])
        return self._add(side, other, *back[side])

    def _add(self, side, other, stamp_ns, msg, size):
        stamps = self._stamps[other]
        lo = bisect.bisect_left(stamps, stamp_ns - self.tolerance_ns)
        hi = bisect.bisect_right(stamps, stamp_ns + self.tolerance_ns)
        if lo == hi:
            i = bisect.bisect_right(self._stamps[side], stamp_ns)
            self._stamps[side].insert(i, stamp_ns)
            self._msgs[side].insert(i, msg)
            self._sizes[side].insert(i, size)
            while len(self._stamps[side]) > 1 and (
                    len(self._stamps[side]) > self.queue_size
                    or (self.max_bytes is not None and sum(self._sizes[side]) > self.max_bytes)):
                self._discard_first(side, 1)
            return None
        j = min(range(lo, hi), key=lambda k: abs(stamps[k] - stamp_ns))
        match_stamp, match = stamps.pop(j), self._msgs[other].pop(j)
        del self._sizes[other][j]
        self._discard_upto(side, stamp_ns)
        self._discard_upto(other, match_stamp)
        for s in SIDES:  # stragglers
            if self._back[s] is not None:
                self._back[s] = None
                self._drop(s, 1)
        self._last[side], self._last[other] = stamp_ns, match_stamp
        self._streak = {s: 0 for s in SIDES}
        self.pairs += 1
        if side == 'left':
            return stamp_ns, msg, match
        return match_stamp, match, msg

    def unmatched_streak(self, side):
        """
        Return the number of messages of `side` discarded unpaired since the last pair.

        Growth means its twin goes missing.
        """
        other_side(side)
        return self._streak[side]

    def _discard_upto(self, side, stamp_ns):
        self._discard_first(side, bisect.bisect_right(self._stamps[side], stamp_ns))

    def _discard_first(self, side, n):
        for queue in (self._stamps, self._msgs, self._sizes):
            del queue[side][:n]
        self._drop(side, n)

    def _drop(self, side, n):
        self._streak[side] += n
        if side == 'left':
            self.dropped_left += n
        else:
            self.dropped_right += n


def other_side(side):
    if side not in SIDES:
        raise ValueError(f"side must be 'left' or 'right', got {side!r}")
    return 'right' if side == 'left' else 'left'


class CameraInfos:
    """
    The recent camera_info messages of each side, by stamp, to pair each image with its own.

    As image_transport's camera subscribers do: an image goes with the camera_info of its
    stamp (within `tolerance_ns`), whichever of the two was received first. `keep` messages
    per side are kept (the newest stamps).
    """

    def __init__(self, tolerance_ns=0, keep=30):
        self.tolerance_ns = tolerance_ns
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
