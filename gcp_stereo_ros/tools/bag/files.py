"""
The bags of gcp-stereo-bag: message types, topics and QoS, reading and writing rosbag2.

The type store is rosbags' Jazzy one, so no ROS install is needed. A bag is read through
`open_bag` and `read_messages`, whose failures on a foreign or damaged file are ValueErrors
naming it, and written through `output_bag`: to a hidden staging sibling, renamed into
place only when complete.
"""
from contextlib import contextmanager
import os
from pathlib import Path
import shutil
from types import SimpleNamespace

from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

PROG = 'gcp-stereo-bag'
IMAGE, INFO, STRING = 'sensor_msgs/msg/Image', 'sensor_msgs/msg/CameraInfo', 'std_msgs/msg/String'
COMPRESSED = 'sensor_msgs/msg/CompressedImage'
DISPARITY, POINTS = 'stereo_msgs/msg/DisparityImage', 'sensor_msgs/msg/PointCloud2'
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
TYPES = SimpleNamespace(**{t.rsplit('/', 1)[1]: TYPESTORE.types[t] for t in (
    IMAGE, COMPRESSED, INFO, STRING, DISPARITY, POINTS, 'sensor_msgs/msg/PointField',
    'sensor_msgs/msg/RegionOfInterest', 'std_msgs/msg/Header', 'builtin_interfaces/msg/Time')})


def _qos(reliability, depth):
    zero = QosTime(0, 0)  # = the middleware default (infinite)
    return Qos(QosHistory.KEEP_LAST, depth, reliability, QosDurability.VOLATILE, zero, zero,
               QosLiveliness.SYSTEM_DEFAULT, zero, False)


SENSOR_QOS = _qos(QosReliability.BEST_EFFORT, 5)  # rclpy's qos_profile_sensor_data
DEFAULT_QOS = _qos(QosReliability.RELIABLE, 10)  # rclpy's default publisher QoS
NODE_OUT_QOS = _qos(QosReliability.RELIABLE, 1)  # the node's publishers
GT = {'gt/frame_name': (STRING, DEFAULT_QOS), 'gt/disparity': (IMAGE, DEFAULT_QOS),
      'gt/valid': (IMAGE, DEFAULT_QOS)}
OUTPUTS = {'disparity': DISPARITY, 'gcp_mask': IMAGE, 'confidence': IMAGE,
           'disparity_confidence': IMAGE, 'depth': IMAGE, 'points2': POINTS}
IMAGE_TYPES = (IMAGE, COMPRESSED)
FRAME_RATE_HZ = 10.0  # make's default frame rate, and that of `play --loop` on a one-stamp bag


def topic_name(namespace, name):
    """
    Return `name` under `namespace` as an absolute topic.

    E.g. ('stereo', 'left/image_rect') -> /stereo/left/image_rect.
    """
    ns = namespace.strip('/')
    return f'/{ns}/{name}' if ns else f'/{name}'


def stamped_header(stamp_ns, frame_id):
    """Return a std_msgs/Header of `stamp_ns` (ns since the epoch) and `frame_id`."""
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return TYPES.Header(stamp=TYPES.Time(sec=sec, nanosec=nanosec), frame_id=frame_id)


@contextmanager
def open_bag(path):
    """Yield an open rosbags Reader; any failure to open it is a ValueError naming `path`."""
    try:
        reader = Reader(path)
        reader.open()
    except Exception as err:  # the parsers of a foreign or corrupt file raise anything
        raise ValueError(f'{path}: not a readable rosbag2: {err}') from None
    try:
        yield reader
    finally:
        reader.close()


def read_messages(reader, path):
    """
    Yield (connection, bag timestamp ns, raw CDR bytes) of every message.

    A truncated or corrupt storage file is a ValueError naming `path`.
    """
    stream = reader.messages()
    while True:
        try:
            item = next(stream)
        except StopIteration:
            return
        except Exception as err:  # sqlite3, mcap, zstd... errors of a damaged file
            raise ValueError(f'{path}: damaged bag, cannot read its messages: {err}') from None
        yield item


def deserialize(raw, connection, timestamp, path):
    try:
        return TYPESTORE.deserialize_cdr(raw, connection.msgtype)
    except Exception as err:  # any malformed CDR
        raise ValueError(f'{path}: {connection.topic} message at {timestamp} ns is not a valid '
                         f'{connection.msgtype}: {err}') from None


@contextmanager
def output_bag(out, storage, force):
    """
    Yield a rosbags Writer on a hidden staging sibling of `out`.

    The bag is moved to `out` only if the block succeeds; the staging folder is removed either
    way, and those of killed runs (their process gone) before this one starts. An existing
    `out` needs `force`.
    """
    out = Path(out)
    if out.exists() and not force:
        raise ValueError(f'{out} exists; pass --force to replace it')
    prefix = f'.{out.name}.partial-'
    for old in out.parent.glob(prefix + '*'):
        pid = old.name[len(prefix):]
        if pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(old, ignore_errors=True)
    staging = out.with_name(f'{prefix}{os.getpid()}')
    staging.mkdir(parents=True)
    try:
        with Writer(staging / out.name, version=Writer.VERSION_LATEST,
                    storage_plugin=StoragePlugin[storage.upper()]) as writer:
            yield writer
        if out.is_dir():
            shutil.rmtree(out)
        elif out.exists():
            out.unlink()
        (staging / out.name).rename(out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _alive(pid):
    """Whether process `pid` runs (another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        pass
    return True
