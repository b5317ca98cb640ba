"""
Output messages from pipeline results, ROS-free.

`types` is any namespace with the message classes Image, DisparityImage and
RegionOfInterest: rclpy's (sensor_msgs.msg / stereo_msgs.msg) in the node, rosbags' in the
bag tools. Fields are passed by keyword, which both accept.
"""
from dataclasses import dataclass

import numpy as np

from .rosimage import array_to_image_fields


def stamp_ns(header):
    """Return a std_msgs/Header's stamp in integer nanoseconds (the sync and bag key)."""
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


FLOAT32_MAX = float(np.finfo(np.float32).max)


@dataclass(frozen=True)
class Geometry:
    f: float = 0.0  # focal length in pixels (0 = unknown)
    t: float = 0.0  # baseline in world units (0 = unknown)
    cx_offset: float = 0.0  # cx_left - cx_right, subtracted from disparities


def geometry(left_info, right_info, size, max_disp):
    """
    Return the stereo geometry of a pair from its left and right sensor_msgs/CameraInfo.

    Either CameraInfo may be None if absent; P all zero in both means uncalibrated. Both
    give Geometry(). Computed as stereo_image_proc does: f = right fx, t = -right Tx / fx.
    Raises ValueError, naming the field, for a CameraInfo that does not fit the images of
    `size` (height, width) matched with `max_disp` disparities: NaN or inf in P, another
    image size, fx <= 0, a baseline t <= 0, principal points at least `max_disp` px apart
    (the published disparities would leave the message's range), or f, t beyond float32.
    """
    if left_info is None or right_info is None:
        return Geometry()
    p = {}
    for side, info in (('left', left_info), ('right', right_info)):
        p[side] = np.asarray(info.p, float)
        if not np.isfinite(p[side]).all():
            raise ValueError(f'{side} camera_info: P holds NaN or inf: {p[side].tolist()}')
        if (info.height, info.width) != tuple(size):
            raise ValueError(f'{side} camera_info is for {info.width}x{info.height} images, '
                             f'the pair is {size[1]}x{size[0]}')
    pl, pr = p['left'], p['right']
    if not (pl.any() or pr.any()):
        return Geometry()
    if not (pl[0] > 0 and pr[0] > 0):
        raise ValueError(f'camera_info: fx = P[0] must be > 0, got left {pl[0]:g}, '
                         f'right {pr[0]:g}')
    f, t, cx_offset = pr[0], -pr[3] / pr[0], pl[2] - pr[2]
    if not t > 0:
        raise ValueError(f'right camera_info: baseline -P[3] / fx = {t:g} must be > 0 '
                         '(the right camera has P[3] = -fx * baseline)')
    if abs(cx_offset) >= max_disp:
        raise ValueError(f'camera_info: the principal points differ by {cx_offset:g} px '
                         f'(left cx - right cx), not within max_disparity {max_disp}')
    if not max(f, t) <= FLOAT32_MAX:
        raise ValueError(f'camera_info: f {f:g} or baseline {t:g} does not fit the float32 '
                         'fields of stereo_msgs/DisparityImage')
    return Geometry(float(f), float(t), float(cx_offset))


def disparity_message(types, header, disp, config, geom, data=lambda a: a):
    """
    Return a stereo_msgs/DisparityImage for a float32 disparity.

    NaN = invalid, published as min_disparity - 1 as the message definition asks. `data`
    converts the uint8 buffer to what the message class wants (array.array('B') for rclpy,
    the numpy array for rosbags).
    """
    border = config.window // 2
    h, w = disp.shape
    out = disp - np.float32(geom.cx_offset) if geom.cx_offset else disp.copy()
    out[np.isnan(out)] = -1.0
    left = min(config.max_disp - 1 + border, w)
    roi = types.RegionOfInterest(x_offset=left, y_offset=border, width=max(w - border - left, 0),
                                 height=max(h - 2 * border, 0), do_rectify=False)
    return types.DisparityImage(
        header=header, image=image_message(types, header, out, '32FC1', data),
        f=geom.f, t=geom.t, valid_window=roi,
        min_disparity=0.0, max_disparity=float(config.max_disp - 1),
        delta_d=1.0 / 16 if config.subpixel else 1.0)


def image_message(types, header, array, encoding, data=lambda a: a):
    """Return a sensor_msgs/Image of a mono8 or 32FC1 array."""
    fields = array_to_image_fields(array, encoding)
    fields['data'] = data(fields['data'])
    return types.Image(header=header, **fields)
