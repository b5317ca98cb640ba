"""gcp-stereo-bag make: stereo pairs of a dataset -> a bag of the node's inputs and the truth."""
import time

import numpy as np
from tqdm import tqdm

from .files import (COMPRESSED, GT, IMAGE, INFO, output_bag, SENSOR_QOS, stamped_header,
                    topic_name, TYPES, TYPESTORE)
from ...evaluation.datasets import list_frames, load_frames
from ...ros.rosimage import array_to_compressed_fields, image_message
from ...ros.sync import SIDES
from ...stereo.images import mask_image


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
    headers = {side: stamped_header(stamp_ns, f'{side}_camera') for side in SIDES}
    if frame.gt is not None:
        known = np.isfinite(frame.gt)
        valid = known if frame.valid is None else known & frame.valid
        msgs['gt/frame_name'] = TYPES.String(data=frame.name)
        msgs['gt/disparity'] = image_message(TYPES, headers['left'],
                                             np.where(known, frame.gt, 0), '32FC1')
        msgs['gt/valid'] = image_message(TYPES, headers['left'], mask_image(valid), 'mono8')
    for side in SIDES:
        msgs[f'{side}/camera_info'] = camera_info(headers[side], frame, side)
    for side in SIDES:
        image = getattr(frame, side)
        if compressed:
            msgs[f'{side}/image_rect/compressed'] = TYPES.CompressedImage(
                header=headers[side], **array_to_compressed_fields(image, compressed))
        else:
            msgs[f'{side}/image_rect'] = image_message(
                TYPES, headers[side], image, 'rgb8' if image.ndim == 3 else 'mono8')
    return msgs


def command(args):
    """Write bag args.out of the frames of args.dataset, as the package says (`make`)."""
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
