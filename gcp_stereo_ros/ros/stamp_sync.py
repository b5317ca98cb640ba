"""
One message of each of several topics by header stamp, ROS-free (message_filters' policies).

point_cloud_node matches its four inputs with it, as stereo_image_proc's does with
message_filters: ExactTime (identical stamps), ApproximateEpsilonTime (stamps at most a
tolerance apart) or, with no tolerance, ApproximateTime (the closest ones), simplified: a
set is complete as soon as the message just added finds, on every other topic, the queued
message closest to its stamp within the tolerance.
"""
import bisect
import math


class StampSync:
    """
    Match one message of each of `names` by stamp (integer nanoseconds).

    `tolerance_ns` 0 asks for identical stamps, math.inf for the closest ones. Each topic
    queues at most `queue_size` messages (the oldest goes first); a complete set takes its
    messages and every older one off the queues. `dropped` counts messages that left a queue
    unmatched.
    """

    def __init__(self, names, queue_size=5, tolerance_ns=0):
        if isinstance(queue_size, bool) or not isinstance(queue_size, int) or queue_size < 1:
            raise ValueError(f'queue_size must be an integer >= 1, got {queue_size!r}')
        if not tolerance_ns >= 0:
            raise ValueError(f'tolerance must be >= 0, got {tolerance_ns!r}')
        self.queue_size = queue_size
        self.tolerance_ns = tolerance_ns
        self.dropped = 0
        self._stamps = {name: [] for name in names}  # ascending, parallel to _msgs
        self._msgs = {name: [] for name in names}

    def add(self, name, stamp_ns, msg):
        """Queue `msg` of topic `name`; return {name: message} once a set is complete."""
        stamps, msgs = self._stamps[name], self._msgs[name]
        i = bisect.bisect_right(stamps, stamp_ns)
        stamps.insert(i, stamp_ns)
        msgs.insert(i, msg)
        if len(stamps) > self.queue_size:
            self._take(name, 0)
            self.dropped += 1
        picks = {}
        for other, queue in self._stamps.items():
            if other == name:
                continue
            j = min(range(len(queue)), key=lambda k: abs(queue[k] - stamp_ns), default=None)
            if j is None or abs(queue[j] - stamp_ns) > self.tolerance_ns:
                return None
            picks[other] = j
        picks[name] = bisect.bisect_left(stamps, stamp_ns)
        out = {}
        for other, j in picks.items():
            self.dropped += j  # older than the matched one: never to be matched
            for _ in range(j):
                self._take(other, 0)
            out[other] = self._take(other, 0)
        return out

    def _take(self, name, j):
        del self._stamps[name][j]
        return self._msgs[name].pop(j)


def tolerance_ns(approximate, tolerance_seconds):
    """Return StampSync's tolerance for stereo_image_proc's two sync parameters."""
    if not approximate:
        return 0
    return round(tolerance_seconds * 1e9) if tolerance_seconds > 0 else math.inf
