"""
gcp-stereo-bag: rosbag2 tools for gcp_stereo_node, no ROS install needed (rosbags, rclpy).

  make  stereo pairs of a dataset -> a bag with the node's input topics and the ground truth
  run   bag in -> bag out with the node's outputs, computed offline exactly as the node does
  play  a bag into a live ROS graph at its recorded timing, like `ros2 bag play`

Bags written by `make` (every topic under --namespace; all messages of a frame carry the
frame's stamp as header stamp and as bag timestamp, the ground truth written first):
  left/image_rect, right/image_rect    sensor_msgs/Image, rgb8 or mono8 as the dataset stores
                                       it; frame_id left_camera, right_camera
  left/camera_info, right/camera_info  sensor_msgs/CameraInfo; when the dataset knows them, f in
                                       K and P and P_right[3] = -f * baseline (principal point
                                       at the image centre), else K = P = 0 (uncalibrated)
  gt/disparity                         sensor_msgs/Image 32FC1, left disparity in px, 0 = unknown
  gt/valid                             sensor_msgs/Image mono8, 255 = pixel scored (ground truth
                                       known and inside the dataset's mask, e.g. non-occluded)
  gt/frame_name                        std_msgs/String, the dataset's frame name
Images and camera_info are recorded with the sensor-data QoS (best effort, volatile, keep
last 5) the node subscribes with; the ground truth with the default QoS (reliable).

`run` pairs left and right images by stamp (the node's sync parameters: exact by default)
and scores a pair against the gt/ messages whose bag timestamp is the pair's stamp. Its
output bag holds every input message (earlier outputs excepted) plus, under the same
namespace and built as the node builds them, `disparity` (stereo_msgs/DisparityImage),
`gcp_mask` (mono8, 255 = GCP) and `confidence` (32FC1; the node sends it only while
subscribed), stamped with the left header and written at the bag timestamp of the image that
completed the pair. Bags are written to a hidden sibling and renamed into place on success.
"""
import argparse
from contextlib import contextmanager
import importlib
import os
from pathlib import Path
import shutil
import sys
import time
from types import SimpleNamespace

import numpy as np
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.errors import WriterError
from rosbags.typesys import get_typestore, Stores, TypesysError
from tqdm import tqdm

from .cli import console_main, positive
from ..evaluation.datasets import list_frames, load_frames
from ..evaluation.metrics import error_rates, THRESHOLDS
from ..evaluation.viz import colorize, save_png
from ..ros import messages
from ..ros.params import config_from_params, load_params_file, make_sync
from ..ros.rosimage import image_to_array
from ..ros.sync import SIDES
from ..stereo.images import mask_image
from ..stereo.pipeline import StereoPipeline

PROG = 'gcp-stereo-bag'
IMAGE, INFO, STRING = 'sensor_msgs/msg/Image', 'sensor_msgs/msg/CameraInfo', 'std_msgs/msg/String'
DISPARITY = 'stereo_msgs/msg/DisparityImage'
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
TYPES = SimpleNamespace(**{t.rsplit('/', 1)[1]: TYPESTORE.types[t] for t in (
    IMAGE, INFO, STRING, DISPARITY, 'sensor_msgs/msg/RegionOfInterest', 'std_msgs/msg/Header',
    'builtin_interfaces/msg/Time')})


def _qos(reliability, depth):
    zero = QosTime(0, 0)  # = the middleware default (infinite)
    return Qos(QosHistory.KEEP_LAST, depth, reliability, QosDurability.VOLATILE, zero, zero,
               QosLiveliness.SYSTEM_DEFAULT, zero, False)


SENSOR_QOS = _qos(QosReliability.BEST_EFFORT, 5)  # rclpy's qos_profile_sensor_data
DEFAULT_QOS = _qos(QosReliability.RELIABLE, 10)  # rclpy's default publisher QoS
NODE_OUT_QOS = _qos(QosReliability.RELIABLE, 5)  # the node's publishers
INPUTS = {f'{side}/{kind}': (msgtype, SENSOR_QOS)
          for kind, msgtype in (('image_rect', IMAGE), ('camera_info', INFO)) for side in SIDES}
GT = {'gt/frame_name': (STRING, DEFAULT_QOS), 'gt/disparity': (IMAGE, DEFAULT_QOS),
      'gt/valid': (IMAGE, DEFAULT_QOS)}
OUTPUTS = {'disparity': DISPARITY, 'gcp_mask': IMAGE, 'confidence': IMAGE}
MATCH_SETTLE_SECONDS = 3.0  # see wait_for_subscribers
# Before exiting: a player exiting right after publishing lost its last best-effort
# messages in 2 of 20 plays, in none of 45 after lingering this long.
LINGER_SECONDS = 1.0


def topic_name(namespace, name):
    """
    Return `name` under `namespace` as an absolute topic.

    E.g. ('stereo', 'left/image_rect') -> /stereo/left/image_rect.
    """
    ns = namespace.strip('/')
    return f'/{ns}/{name}' if ns else f'/{name}'


def _header(stamp_ns, frame_id):
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return TYPES.Header(stamp=TYPES.Time(sec=sec, nanosec=nanosec), frame_id=frame_id)


# ---- bag files --------------------------------------------------------------------------
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
    way. An existing `out` needs `force`.
    """
    out = Path(out)
    if out.exists() and not force:
        raise ValueError(f'{out} exists; pass --force to replace it')
    staging = out.with_name(f'.{out.name}.partial-{os.getpid()}')
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


# ---- make -------------------------------------------------------------------------------
def camera_info(header, frame, side):
    """
    Return the CameraInfo of a rectified camera of `frame`.

    K = P = 0 unless the focal length is known.
    """
    h, w = frame.left.shape[:2]
    f = frame.focal_px or 0.0
    tx = -f * (frame.baseline_m or 0.0) if side == 'right' else 0.0
    p = np.array([f, 0, w / 2, tx, 0, f, h / 2, 0, 0, 0, 1, 0], float) if f else np.zeros(12)
    return TYPES.CameraInfo(
        header=header, height=h, width=w, distortion_model='plumb_bob', d=np.zeros(5),
        k=p.reshape(3, 4)[:, :3].ravel(), r=np.eye(3).ravel(), p=p, binning_x=0, binning_y=0,
        roi=TYPES.RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def frame_messages(frame, stamp_ns):
    """{topic name without namespace: message} of one frame, ground truth first."""
    msgs = {}
    headers = {side: _header(stamp_ns, f'{side}_camera') for side in SIDES}
    if frame.gt is not None:
        known = np.isfinite(frame.gt)
        valid = known if frame.valid is None else known & frame.valid
        msgs['gt/frame_name'] = TYPES.String(data=frame.name)
        msgs['gt/disparity'] = messages.image_message(TYPES, headers['left'],
                                                      np.where(known, frame.gt, 0), '32FC1')
        msgs['gt/valid'] = messages.image_message(TYPES, headers['left'], mask_image(valid),
                                                  'mono8')
    for side in SIDES:
        msgs[f'{side}/camera_info'] = camera_info(headers[side], frame, side)
    for side in SIDES:
        image = getattr(frame, side)
        msgs[f'{side}/image_rect'] = messages.image_message(TYPES, headers[side], image,
                                                            'rgb8' if image.ndim == 3 else 'mono8')
    return msgs


def make(args):
    names = args.frames or list_frames(args.dataset)
    period_ns = round(1e9 / args.rate)
    start_ns = time.time_ns()
    with output_bag(args.out, args.storage, args.force) as writer:
        conns = {name: writer.add_connection(topic_name(args.namespace, name), msgtype,
                                             typestore=TYPESTORE, offered_qos_profiles=[qos])
                 for name, (msgtype, qos) in {**GT, **INPUTS}.items()}
        frames = load_frames(args.dataset, names)
        for i, frame in enumerate(tqdm(frames, total=len(names), unit='frame', leave=False)):
            stamp = start_ns + i * period_ns
            for name, msg in frame_messages(frame, stamp).items():
                writer.write(conns[name], stamp, TYPESTORE.serialize_cdr(msg, conns[name].msgtype))
    print(f'{args.out}: {len(names)} frame(s) at {args.rate:g} Hz ({args.storage})')


# ---- run --------------------------------------------------------------------------------
def check_topics(reader, path, namespace):
    """
    Return {topic: name without namespace} of the inputs and ground truth `run` reads.

    Raises ValueError unless both image topics exist, or if a known topic has the wrong type.
    """
    wanted = {topic_name(namespace, name): (name, msgtype)
              for name, (msgtype, _) in {**INPUTS, **GT}.items()}
    topics = {c.topic: c.msgtype for c in reader.connections}
    for side in SIDES:
        topic = topic_name(namespace, f'{side}/image_rect')
        if topic not in topics:
            raise ValueError(f'{path}: no {topic} topic '
                             f'(topics: {", ".join(sorted(topics)) or "none"}); '
                             'set --namespace if the images are under one')
    for topic, msgtype in topics.items():
        if topic in wanted and msgtype != wanted[topic][1]:
            raise ValueError(f'{path}: {topic} is {msgtype}, expected {wanted[topic][1]}')
    return {topic: name for topic, (name, _) in wanted.items() if topic in topics}


RATE_KEYS = [f'bad{t}' for t in THRESHOLDS] + ['mae']


def print_rates(label, rates):
    tqdm.write(''.join(f'{rates[k]:8.2f}' for k in RATE_KEYS) + f'  {label}')


class Runner:
    """Turns input messages into output messages, pair by pair, as the node does."""

    def __init__(self, pipeline, sync, writer, namespace, png_dir):
        self.pipeline, self.sync, self.writer, self.png_dir = pipeline, sync, writer, png_dir
        self.conns = {name: writer.add_connection(topic_name(namespace, name), msgtype,
                                                  typestore=TYPESTORE,
                                                  offered_qos_profiles=[NODE_OUT_QOS])
                      for name, msgtype in OUTPUTS.items()}
        self.topics = {name: topic_name(namespace, name) for name in INPUTS}
        self.info = dict.fromkeys(SIDES)
        self.gt = {}  # bag timestamp -> {'gt/...': message} until its pair comes
        self.rates = []

    def add(self, name, msg, timestamp):
        """Take one message of input `name` (as in INPUTS or GT) logged at `timestamp`."""
        side = name.split('/')[0]
        if name.startswith('gt/'):
            self.gt.setdefault(timestamp, {})[name] = msg
        elif name.endswith('camera_info'):
            self.info[side] = msg
        else:
            pair = self.sync.add(side, messages.stamp_ns(msg.header), msg)
            if pair is not None:
                self.process(*pair, timestamp)

    def process(self, stamp, left_msg, right_msg, timestamp):
        config = self.pipeline.config
        left = image_to_array(left_msg, self.topics['left/image_rect'])
        right = image_to_array(right_msg, self.topics['right/image_rect'])
        result = self.pipeline(left, right)
        header = left_msg.header
        geom = messages.geometry(self.info['left'], self.info['right'])
        out = {'disparity': messages.disparity_message(TYPES, header, result.disparity,
                                                       config, geom)}
        if result.gcp is not None:
            out['gcp_mask'] = messages.image_message(TYPES, header, mask_image(result.gcp),
                                                     'mono8')
            out['confidence'] = messages.image_message(TYPES, header, result.cof_c, '32FC1')
        for name, msg in out.items():
            self.writer.write(self.conns[name], timestamp,
                              TYPESTORE.serialize_cdr(msg, OUTPUTS[name]))

        gt = self.gt.pop(stamp, {})
        for old in [t for t in self.gt if t < stamp]:  # ground truth of pairs never completed
            del self.gt[old]
        label = gt['gt/frame_name'].data if 'gt/frame_name' in gt else str(stamp)
        if 'gt/disparity' in gt and 'gt/valid' in gt:
            rates = error_rates(result.disparity,
                                image_to_array(gt['gt/disparity'], 'gt/disparity'),
                                image_to_array(gt['gt/valid'], 'gt/valid') > 0)
            self.rates.append(rates)
            print_rates(label, rates)
        if self.png_dir:
            stem = Path(self.png_dir) / label.replace('/', '_')
            save_png(f'{stem}_disparity.png', colorize(result.disparity, config.max_disp))
            if result.gcp is not None:
                save_png(f'{stem}_gcp_mask.png', mask_image(result.gcp))


def run(args):
    values = load_params_file(args.params) if args.params else {}
    convert(run_pipeline(values), values, args)


def run_pipeline(values):
    """Return the pipeline of node parameters `values` for `convert`, its CNN loaded."""
    pipeline = StereoPipeline(config_from_params(values))
    if pipeline.config.use_gcp:
        pipeline.net  # a missing weights file fails here, before any output
    return pipeline


def convert(pipeline, values, args):
    """
    Write bag args.out: bag args.inp plus the outputs of `pipeline`, as `run` describes.

    `values`: the node parameters (the pair sync's); args: the options of `run`.
    """
    sync = make_sync(values)
    with open_bag(args.inp) as reader, output_bag(args.out, args.storage, args.force) as writer:
        names = check_topics(reader, args.inp, args.namespace)
        runner = Runner(pipeline, sync, writer, args.namespace, args.png)
        # outputs of an earlier run
        replaced = {topic_name(args.namespace, name) for name in OUTPUTS}
        copies = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=TYPESTORE,
                                              msgdef=c.msgdef.data or None,
                                              rihs01=c.digest or None,
                                              offered_qos_profiles=c.ext.offered_qos_profiles)
                  for c in reader.connections if c.topic not in replaced}
        if 'gt/disparity' in names.values():
            tqdm.write(''.join(f'{k:>8}' for k in RATE_KEYS) + '  frame')
        lefts = sum(c.msgcount for c in reader.connections
                    if names.get(c.topic) == 'left/image_rect')
        with tqdm(total=lefts, unit='pair', leave=False) as bar:
            for conn, timestamp, raw in read_messages(reader, args.inp):
                if conn.id in copies:
                    writer.write(copies[conn.id], timestamp, raw)
                if conn.topic in names:
                    runner.add(names[conn.topic], deserialize(raw, conn, timestamp, args.inp),
                               timestamp)
                    bar.update(sync.pairs - bar.n)
        if sync.pairs == 0:
            raise ValueError(f'{args.inp}: no left/right image pair with matching stamps')
    if runner.rates:
        print_rates('mean', {k: float(np.mean([r[k] for r in runner.rates])) for k in RATE_KEYS})
        print('(% of scored ground-truth pixels with error > N px; mae in px)')
    print(f'{args.out}: {sync.pairs} pairs processed; images without a twin skipped: '
          f'left {sync.dropped_left}, right {sync.dropped_right}')


# ---- play -------------------------------------------------------------------------------
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
        return qos_profile_sensor_data if connection.msgtype == IMAGE else QoSProfile(depth=10)
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
    then. Hence MATCH_SETTLE_SECONDS more (measured with a node starting up: 1 s lost the
    pair in 1 of 6 runs, 3 s in none of 8).
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


def play(args):
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
                      if c.msgtype == IMAGE and c.topic in publishers and '/gt/' not in c.topic]
            wait_for_subscribers(images, args.wait_subscribers)
            while True:
                start = None
                for conn, timestamp, raw in read_messages(reader, args.inp):
                    if conn.topic not in publishers:
                        continue
                    if start is None:
                        start = (timestamp, time.monotonic())
                    delay = start[1] + (timestamp - start[0]) / 1e9 / args.rate - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    publishers[conn.topic].publish(bytes(raw))  # serialized CDR, published as is
                if start is None:
                    raise ValueError(f'{args.inp}: no message to play')
                if not args.loop:
                    break
            for p in publishers.values():  # reliable subscribers: let them take the last messages
                p.wait_for_all_acked(Duration(seconds=1))
            time.sleep(LINGER_SECONDS)  # best-effort ones too
        finally:
            node.destroy_node()
            rclpy.try_shutdown()


# ---- command line -----------------------------------------------------------------------
STORAGE = {'choices': ('sqlite3', 'mcap'), 'default': 'mcap',
           'help': 'storage plugin of the output bag (default mcap)'}
NAMESPACE = {'default': '', 'metavar': 'NS',
             'help': 'topics under this namespace (default: none, e.g. /left/image_rect)'}


def add_run_options(ap):
    """Add the options of `run` that apply to any bag (all but --in, --out, --force) to `ap`."""
    ap.add_argument('--params', type=Path, metavar='YAML',
                    help='node parameters file, e.g. config/gcp_stereo.yaml '
                         '(default: the node defaults)')
    ap.add_argument('--png', type=Path, metavar='DIR',
                    help='write colour-mapped disparity and GCP-mask PNGs here')
    ap.add_argument('--storage', **STORAGE)
    ap.add_argument('--namespace', **NAMESPACE)


def parser():
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest='command', required=True)
    force = {'action': 'store_true', 'help': 'replace an existing --out'}

    mk = sub.add_parser('make', help='dataset stereo pairs -> bag with the node input topics '
                                     'and ground truth')
    mk.add_argument('--dataset', required=True, metavar='PATH',
                    help='dataset folder in any supported layout (searched recursively), or '
                         "'motorcycle'")
    mk.add_argument('--frames', nargs='+', metavar='NAME',
                    help='frame names (default: all of the dataset)')
    mk.add_argument('--storage', **STORAGE)
    mk.add_argument('--out', required=True, type=Path, metavar='BAG',
                    help='bag to write (a directory)')
    mk.add_argument('--rate', type=positive, default=10.0, metavar='HZ',
                    help='frames per second (default 10)')
    mk.add_argument('--namespace', **NAMESPACE)
    mk.add_argument('--force', **force)

    rn = sub.add_parser('run', help='bag in -> bag out with disparity, gcp_mask, confidence, '
                                    'as the node')
    rn.add_argument('--in', dest='inp', required=True, type=Path, metavar='BAG',
                    help='bag directory, or its .mcap / .db3 file')
    rn.add_argument('--out', required=True, type=Path, metavar='BAG',
                    help='bag to write: the input plus the outputs')
    add_run_options(rn)
    rn.add_argument('--force', **force)

    pl = sub.add_parser('play',
                        help='publish a bag into the live ROS graph at its recorded timing')
    pl.add_argument('--in', dest='inp', required=True, type=Path, metavar='BAG',
                    help='bag directory, or its .mcap / .db3 file')
    pl.add_argument('--rate', type=positive, default=1.0, metavar='R',
                    help='speed factor (default 1)')
    pl.add_argument('--loop', action='store_true',
                    help='play again and again, with the recorded stamps '
                         '(as ros2 bag play --loop)')
    pl.add_argument('--wait-subscribers', type=float, default=5.0, metavar='SECONDS',
                    help='wait up to this long for a subscriber on every image topic '
                         '(ground truth excepted) before publishing (default 5)')
    return ap


@console_main(PROG, errors=(WriterError, TypesysError))
def main(argv=None):
    args = parser().parse_args(argv)
    try:
        {'make': make, 'run': run, 'play': play}[args.command](args)
    except BaseException as err:
        if args.command != 'play':
            err.add_note(f'{args.out} not written')
        raise


if __name__ == '__main__':
    sys.exit(main())
