"""
gcp-stereo-bag: rosbag2 tools for gcp_stereo_node, no ROS install needed (rosbags, rclpy).

  make  stereo pairs of a dataset -> a bag with the node's input topics and the ground truth
  run   bag in -> bag out with the node's outputs, computed offline exactly as the node does
  play  a bag into a live ROS graph at its recorded timing, like `ros2 bag play`

Bags written by `make` (every topic under --namespace; all messages of a frame carry the
frame's stamp as header stamp and as bag timestamp, the ground truth written first):
  left/image_rect, right/image_rect    sensor_msgs/Image, rgb8 or mono8 as the dataset stores
                                       it; frame_id left_camera, right_camera (with
                                       --compressed: left/image_rect/compressed, ...,
                                       sensor_msgs/CompressedImage, png or jpeg)
  left/camera_info, right/camera_info  sensor_msgs/CameraInfo; when the dataset knows them, f in
                                       K and P, P_right[3] = -f * baseline and the principal
                                       points (KITTI calib files, MiddEval3/ETH3D calib.txt,
                                       Motorcycle; else the image centre), else K = P = 0
                                       (uncalibrated)
  gt/disparity                         sensor_msgs/Image 32FC1, left disparity in px, 0 = unknown
  gt/valid                             sensor_msgs/Image mono8, 255 = pixel scored (ground truth
                                       known and inside the dataset's mask, e.g. non-occluded)
  gt/frame_name                        std_msgs/String, the dataset's frame name
Images and camera_info are recorded with the sensor-data QoS (best effort, volatile, keep
last 5) the node subscribes with; the ground truth with the default QoS (reliable).

`run` reads any recording with one stereo pair of image topics (sensor_msgs/Image or
CompressedImage, rectified, or raw with --rectify): --left and --right name them, else the
pair is found (two image topics whose names differ only in left/right), and so are their
camera_info topics (beside the image topics; --left-info, --right-info). It pairs images by
stamp (the node's sync parameters: exact by default) and scores a pair against the gt/
messages whose bag timestamp is the pair's stamp. Its output bag holds every input message
(earlier outputs excepted) plus the --outputs (default disparity, gcp_mask, confidence; also
depth, points2), built as the node builds them, under the stereo namespace (--namespace, or
the part of the image topics before left/right), stamped with the left header and written
at the bag timestamp of the image that completed the pair. A pair the node would skip
(a bad image, a pair over memory_limit_mb) is skipped with a line on stderr. Bags are
written to a hidden sibling and renamed into place on success; Ctrl-C or SIGTERM removes
it, and one left by a killed run is removed by the next run on the same output.
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
from ..ros.camera import camera_model, depth_scale, Rectifier
from ..ros.graph import shm_segment_bytes
from ..ros.params import config_from_params, config_warnings, load_params_file, make_sync
from ..ros.rosimage import array_to_compressed_fields, image_to_array, message_to_array
from ..ros.sync import CameraInfos, SIDES
from ..stereo.images import mask_image
from ..stereo.memory import mmap_large_arrays
from ..stereo.pipeline import StereoPipeline

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
MATCH_SETTLE_SECONDS = 3.0  # see wait_for_subscribers
# Before exiting: a player exiting right after publishing lost its last best-effort
# messages in 2 of 20 plays, in none of 45 after lingering this long.
LINGER_SECONDS = 1.0
FRAME_RATE_HZ = 10.0  # make's default frame rate, and that of `play --loop` on a one-stamp bag


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


# ---- make -------------------------------------------------------------------------------
def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        pass
    return True


def camera_info(header, frame, side):
    """
    Return the CameraInfo of a rectified camera of `frame`.

    K = P = 0 unless the focal length is known; the principal point is the image centre
    unless the frame gives it.
    """
    h, w = frame.left.shape[:2]
    f = frame.focal_px or 0.0
    cx, cy = frame.principal_px or (w / 2, h / 2)
    if side == 'right':
        tx, cx = -f * (frame.baseline_m or 0.0), cx + frame.doffs_px
    else:
        tx = 0.0
    p = np.array([f, 0, cx, tx, 0, f, cy, 0, 0, 0, 1, 0], float) if f else np.zeros(12)
    return TYPES.CameraInfo(
        header=header, height=h, width=w, distortion_model='plumb_bob', d=np.zeros(5),
        k=p.reshape(3, 4)[:, :3].ravel(), r=np.eye(3).ravel(), p=p, binning_x=0, binning_y=0,
        roi=TYPES.RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def input_topics(compressed=None):
    """{topic name without namespace: (msgtype, QoS)} of the inputs `make` writes."""
    image = ('image_rect/compressed', COMPRESSED) if compressed else ('image_rect', IMAGE)
    return {f'{side}/{kind}': (msgtype, SENSOR_QOS)
            for kind, msgtype in (image, ('camera_info', INFO)) for side in SIDES}


def frame_messages(frame, stamp_ns, compressed=None):
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
        if compressed:
            msgs[f'{side}/image_rect/compressed'] = TYPES.CompressedImage(
                header=headers[side], **array_to_compressed_fields(image, compressed))
        else:
            msgs[f'{side}/image_rect'] = messages.image_message(
                TYPES, headers[side], image, 'rgb8' if image.ndim == 3 else 'mono8')
    return msgs


def make(args):
    names = args.frames or list_frames(args.dataset)
    period_ns = round(1e9 / args.rate)
    start_ns = time.time_ns()
    with output_bag(args.out, args.storage, args.force) as writer:
        conns = {name: writer.add_connection(topic_name(args.namespace, name), msgtype,
                                             typestore=TYPESTORE, offered_qos_profiles=[qos])
                 for name, (msgtype, qos) in {**GT, **input_topics(args.compressed)}.items()}
        frames = load_frames(args.dataset, names)
        for i, frame in enumerate(tqdm(frames, total=len(names), unit='frame', leave=False)):
            stamp = start_ns + i * period_ns
            for name, msg in frame_messages(frame, stamp, args.compressed).items():
                writer.write(conns[name], stamp, TYPESTORE.serialize_cdr(msg, conns[name].msgtype))
    print(f'{args.out}: {len(names)} frame(s) at {args.rate:g} Hz ({args.storage}'
          f'{", " + args.compressed if args.compressed else ""})')


# ---- run --------------------------------------------------------------------------------
def _stereo_namespace(left, right):
    """
    Return the part of two image topics before their left/right token; None if not a pair.

    E.g. /cam/left/image_rect + /cam/right/image_rect -> '/cam', /left/image + /right/image
    -> '': the topics differ in one token only, which holds 'left' in one, 'right' in the other.
    """
    a, b = left.strip('/').split('/'), right.strip('/').split('/')
    differ = [i for i, (x, y) in enumerate(zip(a, b)) if x != y]
    if len(a) != len(b) or len(differ) != 1:
        return None
    i = differ[0]
    if 'left' not in a[i] or a[i].replace('left', 'right') != b[i]:
        return None
    return '/' + '/'.join(a[:i]) if i else ''


def _info_topic(image_topic):
    """Return the camera_info topic beside an image topic, as image_transport finds it."""
    base = image_topic.removesuffix('/compressed')
    return base.rsplit('/', 1)[0] + '/camera_info'


def find_topics(reader, path, args):
    """
    Return the topics `run` reads, by role, and the output namespace.

    {'left', 'right': image topic, 'left_info', 'right_info': camera_info topic or None,
    'ns': namespace of the outputs and ground truth}.

    Raises ValueError naming the bag's topics when the stereo pair cannot be found, or when a
    topic is missing or of the wrong type.
    """
    types = {c.topic: c.msgtype for c in reader.connections}
    listing = ', '.join(f'{t} ({m.rsplit("/", 1)[1]})' for t, m in sorted(types.items())) or 'none'
    ns = args.namespace.strip('/')
    if args.left or args.right:
        if not (args.left and args.right):
            raise ValueError('--left and --right go together')
        left, right = args.left, args.right
    else:
        images = [t for t, m in types.items() if m in IMAGE_TYPES
                  and (not ns or t.startswith(f'/{ns}/'))]
        pairs = [(t, u) for t in images for u in images if _stereo_namespace(t, u) is not None]
        if len(pairs) != 1:
            found = ('; stereo pairs: ' + ', '.join(f'{a} + {b}' for a, b in pairs)
                     if pairs else '')
            raise ValueError(f'{path}: {"no" if not pairs else "more than one"} stereo pair of '
                             f'image topics (topics: {listing}){found}; name them with --left '
                             'and --right')
        (left, right), = pairs
    topics = {'left': left, 'right': right,
              'left_info': args.left_info or _info_topic(left),
              'right_info': args.right_info or _info_topic(right)}
    for role, topic in topics.items():
        want = (INFO,) if role.endswith('info') else IMAGE_TYPES
        if topic not in types:
            if role.endswith('info') and not getattr(args, role):
                topics[role] = None  # no calibration: no depth or points2
                continue
            raise ValueError(f'{path}: no {topic} topic (topics: {listing})')
        if types[topic] not in want:
            raise ValueError(f'{path}: {topic} is {types[topic]}, expected {" or ".join(want)}')
    topics['ns'] = f'/{ns}' if ns else _stereo_namespace(left, right) or ''
    return topics


RATE_KEYS = [f'bad{t}' for t in THRESHOLDS] + ['mae', 'density', 'bad3_published',
                                               'near3_published']


def print_rates(label, rates):
    tqdm.write(''.join(f'{rates[k]:{len(k) + 2}.2f}' for k in RATE_KEYS) + f'  {label}')


def warn(text):
    tqdm.write(f'{PROG}: warning: {text}', file=sys.stderr)


class Runner:
    """
    Turns input messages into output messages, pair by pair, as the node does.

    Each pair goes with the camera_info of its images' stamps (sync.CameraInfos), recorded
    before or after them: when the bag has both camera_info topics, a pair waits for them;
    one whose camera_info never comes (a newer one did, or the bag ended) takes the newest,
    with a warning.
    """

    def __init__(self, pipeline, sync, writer, topics, values, outputs, rectify, png_dir):
        self.pipeline, self.sync, self.writer, self.png_dir = pipeline, sync, writer, png_dir
        self.topics, self.values, self.outputs, self.rectify = topics, values, outputs, rectify
        self.conns = {}
        self.rectifier = Rectifier()
        self.infos = CameraInfos(sync.tolerance_ns)
        self.wait = bool(topics.get('left_info') and topics.get('right_info'))
        self.waiting = []  # (stamp, left_msg, right_msg, timestamp) waiting for camera_info
        self.gt = {}  # bag timestamp -> {'gt/...': message} until its pair comes
        self.rates = []
        self.warned = set()
        self.processed = 0
        self.skipped = 0

    def add(self, role, msg, timestamp):
        """Take one message of `role` (left, right, left_info, right_info, gt/...)."""
        if role.startswith('gt/'):
            self.gt.setdefault(timestamp, {})[role] = msg
        elif role.endswith('_info'):
            self.infos.add(role.removesuffix('_info'), messages.stamp_ns(msg.header), msg)
            self.release()
        else:
            pair = self.sync.add(role, messages.stamp_ns(msg.header), msg, len(msg.data))
            if pair is not None:
                self.waiting.append((*pair, timestamp))
                self.release()

    def release(self, end=False):
        """Process the waiting pairs, in order, whose camera_info is here (`end`: all)."""
        while self.waiting:
            stamp, left, right, timestamp = self.waiting[0]
            stamps = {'left': messages.stamp_ns(left.header),
                      'right': messages.stamp_ns(right.header)}
            info = self.infos.match(stamps) if self.wait else dict(self.infos.newest)
            if info is None and (end or self.infos.passed(stamps)):
                info = dict(self.infos.newest)
                self.warn_once('a pair without camera_info of its stamp (within the sync '
                               'tolerance) took the newest camera_info')
            if info is None:
                return
            self.waiting.pop(0)
            self.process(stamp, left, right, timestamp, info)

    def image(self, side, msg, info):
        image = message_to_array(msg, self.topics[side])
        if self.rectify:
            return self.rectifier(side, info[side], image, self.topics[side])
        return image

    def warn_once(self, text):
        if text not in self.warned:
            self.warned.add(text)
            warn(text)

    def process(self, stamp, left_msg, right_msg, timestamp, info):
        config = self.pipeline.config
        try:
            left, right = self.image('left', left_msg, info), self.image('right', right_msg, info)
            model, why = camera_model(info, left.shape, config)
            result = self.pipeline(left, right, camera=depth_scale(model))
        except ValueError as err:  # as the node: say why, go on with the next pair
            self.skipped += 1
            tqdm.write(f'{PROG}: skipping pair at stamp {stamp} ns: {err}', file=sys.stderr)
            return
        self.processed += 1
        if model is None:
            if None not in info.values():  # calibrated, but wrongly
                self.warn_once(f'camera_info ignored (no f, t, depth or points2): {why}')
            elif {'depth', 'points2'} & self.outputs:
                self.warn_once(f'no depth or points2: {why}')
        out = messages.output_messages(
            TYPES, left_msg.header, self.outputs, result, config, model, left,
            self.values.get('use_color', True), not self.values.get('avoid_point_cloud_padding'))
        for name, msg in out.items():
            if name not in self.conns:
                self.conns[name] = self.writer.add_connection(
                    topic_name(self.topics['ns'], name), OUTPUTS[name], typestore=TYPESTORE,
                    offered_qos_profiles=[NODE_OUT_QOS])
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
    """
    Return the pipeline of node parameters `values` for `convert`, its CNN loaded.

    Warnings about the values go to stderr; glibc is told to return freed arrays (a
    long-running process).
    """
    mmap_large_arrays()
    pipeline = StereoPipeline(config_from_params(values))
    if pipeline.config.use_gcp:
        pipeline.net  # a missing weights file fails here, before any output
    for text in config_warnings(pipeline):
        warn(text)
    return pipeline


def convert(pipeline, values, args):
    """
    Write bag args.out: bag args.inp plus the outputs of `pipeline`, as `run` describes.

    `values`: the node parameters (the pair sync's); args: the options of `run`.
    """
    sync = make_sync(values)
    rectify = args.rectify or values.get('rectify', False)
    with open_bag(args.inp) as reader, output_bag(args.out, args.storage, args.force) as writer:
        topics = find_topics(reader, args.inp, args)
        roles = {topics[r]: r for r in ('left', 'right', 'left_info', 'right_info') if topics[r]}
        roles.update({topic_name(topics['ns'], name): name for name in GT})
        types = {c.topic: c.msgtype for c in reader.connections}
        for topic, role in roles.items():
            if role in GT and topic in types and types[topic] != GT[role][0]:
                raise ValueError(f'{args.inp}: {topic} is {types[topic]}, expected {GT[role][0]}')
        runner = Runner(pipeline, sync, writer, topics, values, args.outputs, rectify, args.png)
        # outputs of an earlier run
        replaced = {topic_name(topics['ns'], name) for name in OUTPUTS}
        copies = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=TYPESTORE,
                                              msgdef=c.msgdef.data or None,
                                              rihs01=c.digest or None,
                                              offered_qos_profiles=c.ext.offered_qos_profiles)
                  for c in reader.connections if c.topic not in replaced}
        if any(types.get(t) for t, r in roles.items() if r == 'gt/disparity'):
            tqdm.write(''.join(f'  {k}' for k in RATE_KEYS) + '  frame')
        lefts = sum(c.msgcount for c in reader.connections if c.topic == topics['left'])
        with tqdm(total=lefts, unit='pair', leave=False) as bar:
            for conn, timestamp, raw in read_messages(reader, args.inp):
                if conn.id in copies:
                    writer.write(copies[conn.id], timestamp, raw)
                if conn.topic in roles:
                    runner.add(roles[conn.topic], deserialize(raw, conn, timestamp, args.inp),
                               timestamp)
                    bar.update(sync.pairs - bar.n)
            runner.release(end=True)
        if sync.pairs == 0:
            raise ValueError(f'{args.inp}: no left/right image pair with matching stamps '
                             f'on {topics["left"]} and {topics["right"]}')
        if runner.processed == 0:
            raise ValueError(f'{args.inp}: none of its {sync.pairs} pairs could be processed '
                             '(reasons above)')
    if runner.rates:
        print_rates('mean', {k: float(np.mean([r[k] for r in runner.rates])) for k in RATE_KEYS})
        print('(badN: % of scored ground-truth pixels with error > N px, unpublished ones '
              'filled as the KITTI devkit does; density: % of them published; '
              'bad3_published, near3_published: % of the published with error > 3 px, '
              'more than 3 px too near; mae in px over the published)')
    print(f'{args.out}: {runner.processed} pairs of {topics["left"]} + {topics["right"]} '
          f'processed ({", ".join(sorted(runner.conns))} written), {runner.skipped} skipped; '
          f'images without a twin skipped: left {sync.dropped_left}, right {sync.dropped_right}')


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
                # on (a one-stamp bag at FRAME_RATE_HZ), not at once: that was a flood.
                period = np.median(np.diff(stamps)) if len(stamps) > 1 else 1e9 / FRAME_RATE_HZ
                resume = start[1] + (stamps[-1] - start[0] + period) / 1e9 / args.rate
            for p in publishers.values():  # reliable subscribers: let them take the last messages
                p.wait_for_all_acked(Duration(seconds=1))
            time.sleep(LINGER_SECONDS)  # best-effort ones too
        finally:
            node.destroy_node()
            rclpy.try_shutdown()


# ---- command line -----------------------------------------------------------------------
def _outputs(text):
    names = {n.strip() for n in text.split(',') if n.strip()}
    unknown = names - set(OUTPUTS)
    if unknown or not names:
        raise argparse.ArgumentTypeError(f'unknown output(s) {", ".join(sorted(unknown))}; '
                                         f'choose from {",".join(OUTPUTS)}')
    return names


STORAGE = {'choices': ('sqlite3', 'mcap'), 'default': 'mcap',
           'help': 'storage plugin of the output bag (default mcap)'}


def add_run_options(ap):
    """Add the options of `run` that apply to any bag (all but --in, --out, --force) to `ap`."""
    ap.add_argument('--params', type=Path, metavar='YAML',
                    help='node parameters file, e.g. config/gcp_stereo.yaml, or what `ros2 '
                         'param dump` wrote (default: the node defaults)')
    ap.add_argument('--left', metavar='TOPIC',
                    help='left image topic, sensor_msgs/Image or CompressedImage (default: '
                         'the one stereo pair of image topics in the bag)')
    ap.add_argument('--right', metavar='TOPIC', help='right image topic (with --left)')
    ap.add_argument('--left-info', metavar='TOPIC',
                    help='left camera_info topic (default: camera_info beside the left images, '
                         'if the bag has it)')
    ap.add_argument('--right-info', metavar='TOPIC', help='right camera_info topic')
    ap.add_argument('--rectify', action='store_true',
                    help='the images are raw: rectify them with the camera_info K, D, R, P '
                         "(default: the params file's rectify, else false)")
    ap.add_argument('--outputs', type=_outputs, default={'disparity', 'gcp_mask', 'confidence'},
                    metavar='LIST',
                    help=f'comma-separated outputs to write, of {",".join(OUTPUTS)} (default '
                         'disparity,gcp_mask,confidence; depth and points2 need camera_info)')
    ap.add_argument('--png', type=Path, metavar='DIR',
                    help='write colour-mapped disparity and GCP-mask PNGs here')
    ap.add_argument('--storage', **STORAGE)
    ap.add_argument('--namespace', default='', metavar='NS',
                    help='look for the stereo pair under this namespace and write the outputs '
                         'there (default: the namespace of the image topics)')


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
    mk.add_argument('--rate', type=positive, default=FRAME_RATE_HZ, metavar='HZ',
                    help=f'frames per second (default {FRAME_RATE_HZ:g})')
    mk.add_argument('--namespace', default='', metavar='NS',
                    help='topics under this namespace (default: none, e.g. /left/image_rect)')
    mk.add_argument('--compressed', choices=('png', 'jpeg'),
                    help='write sensor_msgs/CompressedImage on left/image_rect/compressed, '
                         'right/image_rect/compressed, as image_transport does (png is '
                         'lossless; jpeg quality 95)')
    mk.add_argument('--force', **force)

    rn = sub.add_parser('run', help='bag in -> bag out with disparity, gcp_mask, confidence, '
                                    'depth, points2, as the node')
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
                    help='play again and again, with the recorded stamps (as ros2 bag play '
                         '--loop), each pass one frame period after the last (the median '
                         f'step between stamps; {1 / FRAME_RATE_HZ:g} s for a bag of one stamp)')
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
