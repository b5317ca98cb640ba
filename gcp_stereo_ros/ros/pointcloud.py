"""
What a disparity gives, ROS-free: REP 118 depth and organized points2 messages.

Shared by gcp_stereo_node (the disparity it matched) and point_cloud_node (any
stereo_msgs/DisparityImage, as stereo_image_proc's point_cloud_node takes it). `types` and
`data` are as in messages.py.
"""
import numpy as np

from .rosimage import image_message

FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32
_FLOATS = {'32FC1': np.dtype('<f4'), '64FC1': np.dtype('<f8')}


def geometry_messages(types, header, wanted, disparity, model, color=None, padded=True,
                      data=np.asarray):
    """
    Return {name: message} of 'depth' and 'points2' in `wanted` for a disparity x_l - x_r.

    `disparity` is float32 (H, W), NaN = invalid; `model` a camera.StereoModel, or None (no
    calibration): then every point and depth is NaN, as stereo_image_proc publishes them.
    `color` ((H, W) gray or (H, W, 3) RGB) colours points2 (None: no rgb field).
    """
    if model is None:
        depth = np.full(disparity.shape, np.nan, np.float32)
        points = np.full(disparity.shape + (3,), np.nan, np.float32)
    else:
        depth = model.depth(disparity) if 'depth' in wanted else None
        points = model.points(disparity) if 'points2' in wanted else None
    out = {}
    if 'depth' in wanted:
        out['depth'] = image_message(types, header, depth, '32FC1', data)
    if 'points2' in wanted:
        out['points2'] = points_message(types, header, points, color, padded, data)
    return out


def points_message(types, header, points, color=None, padded=True, data=np.asarray):
    """
    Return an organized sensor_msgs/PointCloud2 of (H, W, 3) float32 points (NaN = invalid).

    Laid out as stereo_image_proc's points2: float32 x, y, z, then with `color` ((H, W)
    uint8 or uint16 gray, or (H, W, 3) uint8 RGB) an rgb field, a float32 whose bytes are
    b, g, r, 0. `padded`: 16 bytes a point without colour, 32 with (x, y, z, pad, rgb,
    pad); else 12 and 16.
    """
    h, w = points.shape[:2]
    slots = (4 if padded else 3) + ((4 if padded else 1) if color is not None else 0)
    cloud = np.zeros((h, w, slots), np.float32)
    cloud[:, :, :3] = points
    fields = [types.PointField(name=n, offset=4 * i, datatype=FLOAT32, count=1)
              for i, n in enumerate('xyz')]
    if color is not None:
        c = np.asarray(color)
        c = (c >> 8 if c.dtype == np.uint16 else c).astype(np.uint32)  # mono16: high byte
        packed = c * 0x010101 if c.ndim == 2 else c[:, :, 0] << 16 | c[:, :, 1] << 8 | c[:, :, 2]
        at = 4 if padded else 3
        cloud[:, :, at] = packed.view(np.float32)
        fields.append(types.PointField(name='rgb', offset=4 * at, datatype=FLOAT32, count=1))
    return types.PointCloud2(
        header=header, height=h, width=w, fields=fields, is_bigendian=False,
        point_step=4 * slots, row_step=4 * slots * w, data=data(cloud.reshape(-1).view(np.uint8)),
        is_dense=False)


def disparity_of(msg, model, topic='disparity'):
    """
    Return the disparity x_l - x_r (float32, NaN = invalid) of a stereo_msgs/DisparityImage.

    Its image holds d - (cx_left - cx_right) (so that Z = f * T / d), added back here with
    `model`'s principal points (none without a model); values below min_disparity, NaN and
    inf are invalid. The image is 32FC1 as the message definition says, or 64FC1; with no
    encoding, whichever of the two the data size gives (stereo_image_proc's test fixture
    sends float64 data so). Raises ValueError naming `topic` when the data does not fit.
    """
    image = msg.image
    h, w, step = int(image.height), int(image.width), int(image.step)
    data = image.data
    raw = np.asarray(data, np.uint8) if isinstance(data, (list, tuple)) else np.frombuffer(
        data, np.uint8)
    if not (h and w):
        raise ValueError(f'{topic}: empty disparity image of {w}x{h} pixels')
    if image.encoding:
        if image.encoding not in _FLOATS:
            raise ValueError(f'{topic}: disparity encoding {image.encoding!r}; expected 32FC1')
        dtype = _FLOATS[image.encoding]
    else:  # no encoding: the data size says which
        dtype = _FLOATS['64FC1' if raw.size == h * w * 8 else '32FC1']
        step = raw.size // h
    if step < w * dtype.itemsize or raw.size != h * step:
        raise ValueError(f'{topic}: data holds {raw.size} bytes, not step * height = {step} * '
                         f'{h} for {w} {dtype.name} disparities a row')
    if image.is_bigendian:
        dtype = dtype.newbyteorder('>')
    d = raw.reshape(h, step)[:, :w * dtype.itemsize].view(dtype).astype(np.float32)
    with np.errstate(invalid='ignore'):
        d[~(np.isfinite(d) & (d >= np.float32(msg.min_disparity)))] = np.nan
    return d + np.float32(model.cx_offset) if model is not None else d
