"""
gcp-stereo-bag run: a recording in, a bag out with the node's outputs, as the node makes them.

Pairs by stamp with the node's sync, each pair with the camera_info of its stamp, optionally
rectified, scored against the gt/ topics of a bag that `make` wrote. With `align` (the default) the
right view's misalignment is followed as the node follows it (`drift.Monitor`), estimated on
every pair (the node: on its cadence); each pair's estimate is printed with what was applied.
Raw input (`rectify`): the correction folds into the right view's rectification maps.
"""
from pathlib import Path
import sys

import numpy as np
from tqdm import tqdm

from .files import (deserialize, GT, NODE_OUT_QOS, open_bag, output_bag, OUTPUTS, PROG,
                    read_messages, topic_name, TYPES, TYPESTORE)
from .topics import find_topics
from ...evaluation.metrics import error_rates, THRESHOLDS
from ...evaluation.viz import disparity_picture, save_png
from ...ros import messages
from ...ros.camera import camera_model, depth_scale, Rectifier
from ...ros.cnn_setup import config_warnings, load_cnn
from ...ros.params import config_from_params, load_params_file
from ...ros.rosimage import image_to_array, message_to_array
from ...ros.sync import CameraInfos, image_sync
from ...stereo.alignment import Misalignment
from ...stereo.drift import Monitor
from ...stereo.images import mask_image
from ...stereo.memory import mmap_large_arrays
from ...stereo.pipeline import StereoPipeline


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
        self.waiting = []  # (left_msg, right_msg, timestamp) waiting for camera_info
        self.gt = {}  # bag timestamp -> {'gt/...': message} until its pair comes
        self.rates = []
        self.warned = set()
        self.processed = 0
        self.skipped = 0
        self.drift = Monitor(every=True)

    def add(self, role, msg, timestamp):
        """Take one message of `role` (left, right, left_info, right_info, gt/...)."""
        if role.startswith('gt/'):
            self.gt.setdefault(timestamp, {})[role] = msg
        elif role.endswith('_info'):
            self.infos.add(role.removesuffix('_info'), messages.stamp_ns(msg.header), msg)
            self.release()
        else:
            self.paired(self.sync.add(role, messages.stamp_ns(msg.header), msg, len(msg.data)),
                        timestamp)

    def paired(self, pair, timestamp):
        """Queue a pair of the sync (None: none) for its camera_info; process what can be."""
        if pair is not None:
            self.waiting.append((pair['left'], pair['right'], timestamp))
            self.release()

    def finish(self, timestamp):
        """At the end of the bag: the pairs the sync still waits for, then every waiting one."""
        while (pair := self.sync.flush()) is not None:
            self.paired(pair, timestamp)
        self.release(end=True)

    def release(self, end=False):
        """Process the waiting pairs, in order, whose camera_info is here (`end`: all)."""
        while self.waiting:
            left, right, timestamp = self.waiting[0]
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
            self.process(stamps['left'], left, right, timestamp, info)

    def rectified(self, side, image, info, misalignment=None):
        """Return the decoded `image` of `side`, rectified with `rectify` (and `misalignment`)."""
        if self.rectify:
            return self.rectifier(side, info[side], image, self.topics[side], misalignment)
        return image

    def warn_once(self, text):
        if text not in self.warned:
            self.warned.add(text)
            warn(text)

    def process(self, stamp, left_msg, right_msg, timestamp, info):
        config = self.pipeline.config
        try:
            raw = {side: message_to_array(msg, self.topics[side])
                   for side, msg in (('left', left_msg), ('right', right_msg))}
            left, right = (self.rectified(side, raw[side], info) for side in ('left', 'right'))
            model, why = camera_model(info, left.shape, config)
            align = self.drift.before(left, right, config, self.values)
            applied = align
            if self.rectify and align is not None and align.known:  # one resampling
                right = self.rectified('right', raw['right'], info, align)
                align = Misalignment(False, reason='undone in the rectification', cause='none')
            result = self.pipeline(left, right, camera=depth_scale(model), misalignment=align)
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
        if applied is not None and self.drift.last is not None:
            done = (f'applied {applied.largest:.2f} px (smoothed over {applied.matches} '
                    'estimates)' if applied.known else f'not applied: {applied.reason}')
            tqdm.write(f'{label}: {self.drift.last.summary()}; {done}')
        if 'gt/disparity' in gt and 'gt/valid' in gt:
            rates = error_rates(result.disparity,
                                image_to_array(gt['gt/disparity'], 'gt/disparity'),
                                image_to_array(gt['gt/valid'], 'gt/valid') > 0)
            self.rates.append(rates)
            print_rates(label, rates)
        if self.png_dir:
            stem = Path(self.png_dir) / label.replace('/', '_')
            save_png(f'{stem}_disparity.png', disparity_picture(result.disparity, config.max_disp))
            if result.gcp is not None:
                save_png(f'{stem}_gcp_mask.png', mask_image(result.gcp))


def command(args):
    """Write bag args.out: bag args.inp with the node's outputs, as `run` says."""
    values = load_params_file(args.params) if args.params else {}
    convert(run_pipeline(values, args.params), values, args)


def run_pipeline(values, params=None):
    """
    Return the pipeline of node parameters `values` for `convert`, its CNN loaded.

    `params`: the file the values came from, which a ValueError for an invalid value (or
    combination, e.g. P1 > P2) names. Warnings about the values go to stderr; glibc is
    told to return freed arrays (a long-running process).
    """
    mmap_large_arrays()
    try:
        config = config_from_params(values)
    except ValueError as err:
        raise ValueError(f'{params or "node parameters"}: {err}') from None
    pipeline = load_cnn(StereoPipeline(config))  # weights that cannot work: before any output
    for text in config_warnings(pipeline):
        warn(text)
    return pipeline


def convert(pipeline, values, args):
    """
    Write bag args.out: bag args.inp plus the outputs of `pipeline`, as `run` describes.

    `values`: the node parameters (the pair sync's); args: the options of `run`.
    """
    sync = image_sync(values)
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
        timestamp = None  # of the last message read
        with tqdm(total=lefts, unit='pair', leave=False) as bar:
            for conn, timestamp, raw in read_messages(reader, args.inp):
                if conn.id in copies:
                    writer.write(copies[conn.id], timestamp, raw)
                if conn.topic in roles:
                    runner.add(roles[conn.topic], deserialize(raw, conn, timestamp, args.inp),
                               timestamp)
                    bar.update(sync.sets - bar.n)
            runner.finish(timestamp)
        if sync.sets == 0:
            raise ValueError(f'{args.inp}: no left/right image pair with matching stamps '
                             f'on {topics["left"]} and {topics["right"]}')
        if runner.processed == 0:
            raise ValueError(f'{args.inp}: none of its {sync.sets} pairs could be processed '
                             '(reasons above)')
    if runner.rates:
        print_rates('mean', {k: float(np.mean([r[k] for r in runner.rates])) for k in RATE_KEYS})
        print('(badN: % of scored ground-truth pixels with error > N px, unpublished ones '
              'filled as the KITTI devkit does; density: % of them published; '
              'bad3_published, near3_published: % of the published with error > 3 px, '
              'more than 3 px too near; mae in px over the published)')
    print(f'{args.out}: {runner.processed} pairs of {topics["left"]} + {topics["right"]} '
          f'processed ({", ".join(sorted(runner.conns))} written), {runner.skipped} skipped; '
          'images without a twin skipped: '
          + ', '.join(f'{side} {n}' for side, n in sync.dropped.items()))
