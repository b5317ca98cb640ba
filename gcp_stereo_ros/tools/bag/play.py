"""gcp-stereo-bag play: a bag into a live ROS graph at its recorded timing (rclpy)."""
import importlib
import sys
import time

import numpy as np
from rosbags.interfaces import QosHistory

from .files import FRAME_RATE_HZ, IMAGE_TYPES, open_bag, PROG, read_messages
from ...ros.graph import shm_segment_bytes

MATCH_SETTLE_SECONDS = 3.0  # see wait_for_subscribers
# s before exiting, for best-effort subscribers to take the last messages (chosen by
# experiment: doc/notes/implementation_history.md)
LINGER_SECONDS = 1.0


def ros_qos(connection):
    """
    Return the rclpy QoS for replaying `connection`.

    History, depth, reliability and durability of its first recorded profile (depth 10 if not
    recorded), else the sensor-data QoS for images and the default QoS for the rest.
    """
    from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                           qos_profile_sensor_data)

    def policy(enum, value):
        return enum.SYSTEM_DEFAULT if value.name == 'UNKNOWN' else enum[value.name]

    if not connection.ext.offered_qos_profiles:
        return (qos_profile_sensor_data if connection.msgtype in IMAGE_TYPES
                else QoSProfile(depth=10))
    p = connection.ext.offered_qos_profiles[0]
    return QoSProfile(history=(HistoryPolicy.KEEP_ALL if p.history == QosHistory.KEEP_ALL
                               else HistoryPolicy.KEEP_LAST),
                      depth=p.depth or 10, reliability=policy(ReliabilityPolicy, p.reliability),
                      durability=policy(DurabilityPolicy, p.durability))


def ros_message_class(msgtype):
    """Return the rclpy class of 'pkg/msg/Name', or None if that package is not installed."""
    package, _, name = msgtype.rpartition('/')
    try:
        return getattr(importlib.import_module(package.replace('/', '.')), name)
    except (ImportError, AttributeError):
        return None


def wait_for_subscribers(publishers, seconds):
    """
    Wait up to `seconds` until every publisher has a matched subscriber; warn about the rest.

    DDS matches the two ends separately, each on the other's discovery traffic: a subscriber
    matched here may not have matched this publisher yet, and drops what it sends until
    then. Hence MATCH_SETTLE_SECONDS more (chosen by experiment:
    doc/notes/implementation_history.md).
    """
    deadline = time.monotonic() + seconds
    while any(p.get_subscription_count() == 0 for p in publishers) and time.monotonic() < deadline:
        time.sleep(0.01)
    missing = [p.topic_name for p in publishers if p.get_subscription_count() == 0]
    if missing and seconds > 0:
        print(f'{PROG} play: no subscriber on {", ".join(missing)} after {seconds:g} s; '
              'playing anyway', file=sys.stderr)
    elif publishers and seconds > 0:
        time.sleep(MATCH_SETTLE_SECONDS)


def command(args):
    """Publish bag args.inp as `play` says, then linger for the last messages."""
    import rclpy  # only `play` joins a ROS graph
    from rclpy.duration import Duration
    from rclpy.signals import SignalHandlerOptions

    with open_bag(args.inp) as reader:
        # Ctrl-C: KeyboardInterrupt
        rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node('gcp_stereo_bag_player')
        try:
            publishers = {}
            for c in reader.connections:
                cls = ros_message_class(c.msgtype)
                if cls is None:
                    print(f'{PROG} play: skipping {c.topic}: no rclpy message class for '
                          f'{c.msgtype}', file=sys.stderr)
                elif c.topic not in publishers:
                    publishers[c.topic] = node.create_publisher(cls, c.topic, ros_qos(c))
            if not publishers:
                raise ValueError(f'{args.inp}: no topic with a message type known here')
            images = [publishers[c.topic] for c in reader.connections
                      if c.msgtype in IMAGE_TYPES and c.topic in publishers
                      and '/gt/' not in c.topic]
            wait_for_subscribers(images, args.wait_subscribers)
            segment, too_large = shm_segment_bytes(), set()
            resume = time.monotonic()
            while True:
                start, stamps = None, []  # stamps: the pass's distinct timestamps
                for conn, timestamp, raw in read_messages(reader, args.inp):
                    if conn.topic not in publishers:
                        continue
                    if start is None:
                        start = (timestamp, resume)
                    if not stamps or timestamp != stamps[-1]:
                        stamps.append(timestamp)
                    delay = start[1] + (timestamp - start[0]) / 1e9 / args.rate - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    if len(raw) > segment and conn.topic not in too_large:
                        too_large.add(conn.topic)
                        print(f'{PROG} play: warning: {conn.topic} has messages of '
                              f'{len(raw) / (1 << 20):.1f} MiB, more than the '
                              f'{segment / (1 << 20):g} MiB Fast DDS shared-memory segment '
                              '(FASTRTPS_DEFAULT_PROFILES_FILE): subscribers on this host will '
                              'likely lose them; raise segment_size in the profile',
                              file=sys.stderr)
                    publishers[conn.topic].publish(bytes(raw))  # serialized CDR, published as is
                if start is None:
                    raise ValueError(f'{args.inp}: no message to play')
                if not args.loop:
                    break
                # The next pass one frame period after the last stamp, as a camera would go
                # on (a one-stamp bag at FRAME_RATE_HZ), not at once, which floods the graph.
                period = np.median(np.diff(stamps)) if len(stamps) > 1 else 1e9 / FRAME_RATE_HZ
                resume = start[1] + (stamps[-1] - start[0] + period) / 1e9 / args.rate
            for p in publishers.values():  # reliable subscribers: let them take the last messages
                p.wait_for_all_acked(Duration(seconds=1))
            time.sleep(LINGER_SECONDS)  # best-effort ones too
        finally:
            node.destroy_node()
            rclpy.try_shutdown()
