"""
Output messages from pipeline results, ROS-free.

`types` is any namespace with the message classes Image, DisparityImage, RegionOfInterest,
PointCloud2 and PointField: rclpy's (sensor_msgs.msg / stereo_msgs.msg) in the node,
rosbags' in the bag tools. Fields are passed by keyword, which both accept. `data`
converts a uint8 numpy buffer to what the message class wants (array.array('B') for
rclpy, the numpy array itself for rosbags).
"""
import numpy as np

from .rosimage import array_to_image_fields
from ..stereo.images import mask_image
from ..stereo.postprocess import valid_window

OUTPUTS = ('disparity', 'gcp_mask', 'confidence', 'disparity_confidence', 'depth', 'points2')
FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32


def stamp_ns(header):
    """Return a std_msgs/Header's stamp in integer nanoseconds (the sync and bag key)."""
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def _same(array):
    return array


def output_messages(types, header, wanted, result, config, model, left, use_color=True,
                    padded=True, data=_same):
    """
    Return {name: message} of the outputs in `wanted` (names of OUTPUTS) for one pair.

    `result` is the pipeline's StereoResult, `model` the camera.StereoModel (None: no
    calibration, so no depth or points2 and f = t = 0), `left` the left image array the
    pipeline matched (the colour of points2). gcp_mask and confidence exist only with GCPs,
    disparity_confidence only with a confidence fit (StereoResult.confidence).
    """
    out = {}
    if 'disparity' in wanted:
        out['disparity'] = disparity_message(types, header, result.disparity, config, model,
                                             data)
    if result.gcp is not None:
        if 'gcp_mask' in wanted:
            out['gcp_mask'] = image_message(types, header, mask_image(result.gcp), 'mono8',
                                            data)
        if 'confidence' in wanted:
            out['confidence'] = image_message(types, header, result.cof_c, '32FC1', data)
    if result.confidence is not None and 'disparity_confidence' in wanted:
        out['disparity_confidence'] = image_message(types, header, result.confidence, '32FC1',
                                                    data)
    if model is not None:
        if 'depth' in wanted:
            out['depth'] = image_message(types, header, model.depth(result.disparity),
                                         '32FC1', data)
        if 'points2' in wanted:
            out['points2'] = points_message(types, header, model.points(result.disparity),
                                            left if use_color else None, padded, data)
    return out


def disparity_message(types, header, disp, config, model=None, data=_same):
    """
    Return a stereo_msgs/DisparityImage for a float32 disparity x_left - x_right.

    As stereo_image_proc: the published disparity is d - (cx_left - cx_right), so that
    Z = f * t / d, with f and t of the camera model (0 without one), and min_disparity,
    max_disparity bound the values the search could give (min_disparity is never -0.0).
    Invalid pixels (NaN in `disp`) are published as min_disparity - 1, the one value below
    the range: what stereo_image_proc publishes (OpenCV's invalid value), what its
    point_cloud node (reprojectImageTo3D's missing values) and disparity_view read as
    invalid. valid_window is the region where the matching window stays inside the image
    (postprocess.valid_window): no valid disparity lies outside it.
    """
    h, w = disp.shape
    offset = np.float32(model.cx_offset if model is not None else 0.0)
    low, high = np.float32(0.0) - offset, np.float32(config.max_disp - 1) - offset
    out = disp - offset
    out[np.isnan(out)] = low - 1
    x0, y0, x1, y1 = valid_window(config, (h, w))
    roi = types.RegionOfInterest(x_offset=x0, y_offset=y0, width=x1 - x0, height=y1 - y0,
                                 do_rectify=False)
    return types.DisparityImage(
        header=header, image=image_message(types, header, out, '32FC1', data),
        f=float(model.fx) if model is not None else 0.0,
        t=float(model.baseline) if model is not None else 0.0,
        valid_window=roi, min_disparity=float(low), max_disparity=float(high),
        delta_d=config.downsample / 16 if config.subpixel else float(config.downsample))


def image_message(types, header, array, encoding, data=_same):
    """Return a sensor_msgs/Image of a mono8 or 32FC1 array."""
    fields = array_to_image_fields(array, encoding)
    fields['data'] = data(fields['data'])
    return types.Image(header=header, **fields)


def points_message(types, header, points, color=None, padded=True, data=_same):
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
