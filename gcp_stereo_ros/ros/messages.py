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


@dataclass(frozen=True)
class Geometry:
    f: float = 0.0  # focal length in pixels (0 = unknown)
    t: float = 0.0  # baseline in world units (0 = unknown)
    cx_offset: float = 0.0  # cx_left - cx_right, subtracted from disparities


def geometry(left_info, right_info):
    """
    Return the stereo geometry from the left and right sensor_msgs/CameraInfo.

    Either CameraInfo may be None if absent. Computed as stereo_image_proc does:
    f = right fx, t = -right Tx / fx.
    """
    if left_info is None or right_info is None:
        return Geometry()
    pl, pr = np.asarray(left_info.p, float), np.asarray(right_info.p, float)
    if pr[0] <= 0:
        return Geometry()
    return Geometry(float(pr[0]), float(-pr[3] / pr[0]), float(pl[2] - pr[2]))


def disparity_message(types, header, disp, config, geom, data=lambda a: a):
    """
    Return a stereo_msgs/DisparityImage for a float32 disparity.

    NaN = invalid, published as min_disparity - 1 as the message definition asks. `data`
    converts the uint8 buffer to what the message class wants (array.array('B') for rclpy,
    the numpy array for rosbags).
    """
    f = config.downsample  # matched at 1/f resolution: borders in full-size pixels
    border = config.window // 2 * f
    h, w = disp.shape
    out = disp - np.float32(geom.cx_offset) if geom.cx_offset else disp.copy()
    out[np.isnan(out)] = -1.0
    left = min((config.matched_disp - 1) * f + border, w)
    roi = types.RegionOfInterest(x_offset=left, y_offset=border, width=max(w - border - left, 0),
                                 height=max(h - 2 * border, 0), do_rectify=False)
    return types.DisparityImage(
        header=header, image=image_message(types, header, out, '32FC1', data),
        f=geom.f, t=geom.t, valid_window=roi,
        min_disparity=0.0, max_disparity=float(config.max_disp - 1),
        delta_d=f / 16 if config.subpixel else float(f))


def image_message(types, header, array, encoding, data=lambda a: a):
    """Return a sensor_msgs/Image of a mono8 or 32FC1 array."""
    fields = array_to_image_fields(array, encoding)
    fields['data'] = data(fields['data'])
    return types.Image(header=header, **fields)
