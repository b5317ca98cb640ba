"""
Output messages from pipeline results, ROS-free.

`types` is any namespace with the message classes Image, DisparityImage, RegionOfInterest,
PointCloud2 and PointField: rclpy's (sensor_msgs.msg / stereo_msgs.msg) in the node,
rosbags' in the bag tools. Fields are passed by keyword, which both accept. `data`
converts a uint8 numpy buffer to what the message class wants (array.array('B') for
rclpy, the numpy array itself for rosbags).
"""
import cv2
import numpy as np

from .pointcloud import geometry_messages
from .rosimage import image_message
from ..stereo.images import mask_image
from ..stereo.postprocess import valid_window

OUTPUTS = ('disparity', 'gcp_mask', 'confidence', 'disparity_confidence', 'depth', 'points2',
           'disparity_color')


def stamp_ns(header):
    """Return a std_msgs/Header's stamp in integer nanoseconds (the sync and bag key)."""
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def output_messages(types, header, wanted, result, config, model, left, use_color=True,
                    padded=True, data=np.asarray):
    """
    Return {name: message} of the outputs in `wanted` (names of OUTPUTS) for one pair.

    `result` is the pipeline's StereoResult, `model` the camera.StereoModel (None: no
    calibration, so no depth or points2 and f = t = 0), `left` the left image array the
    pipeline matched (the colour of points2). gcp_mask and confidence exist only with GCPs,
    disparity_confidence only with a confidence fit (StereoResult.disparity_confidence);
    disparity_color is the disparity colour-mapped (bgr8, `color_map`).
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
    if result.disparity_confidence is not None and 'disparity_confidence' in wanted:
        out['disparity_confidence'] = image_message(
            types, header, result.disparity_confidence, '32FC1', data)
    if 'disparity_color' in wanted:
        out['disparity_color'] = image_message(
            types, header, color_map(result.disparity, config.max_disp), 'bgr8', data)
    if model is not None and wanted & {'depth', 'points2'}:
        out.update(geometry_messages(types, header, wanted, result.disparity, model,
                                     left if use_color else None, padded, data))
    return out


def color_map(disp, max_disp):
    """
    Return (H, W, 3) uint8 RGB of a disparity for viewers: jet over 0 .. max_disp - 1.

    The scale is fixed, so a colour means the same disparity in every frame; invalid (NaN)
    pixels are black.
    """
    scaled = np.nan_to_num(disp * np.float32(255 / max(max_disp - 1, 1)), nan=0.0)
    bgr = cv2.applyColorMap(np.clip(scaled, 0, 255).astype(np.uint8), cv2.COLORMAP_JET)
    bgr[np.isnan(disp)] = 0
    return np.ascontiguousarray(bgr[:, :, ::-1])


def disparity_message(types, header, disp, config, model=None, data=np.asarray):
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
