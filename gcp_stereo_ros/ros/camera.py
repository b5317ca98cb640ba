"""
The stereo camera model of a pair of sensor_msgs/CameraInfo, ROS-free (numpy, OpenCV).

As image_geometry's StereoCameraModel: the rectified left camera of P_left, the baseline
T = -P_right[0,3] / P_right[0,0], the reprojection matrix Q; depth and organized 3-D
points of a disparity image; and rectification of raw images from K, D, R, P. Works on
any object with the CameraInfo fields (rclpy's or rosbags' messages).
"""
from dataclasses import dataclass

import cv2
import numpy as np

from ..stereo.alignment import fold

FLOAT32_MAX = float(np.finfo(np.float32).max)
# distortion_model -> the numbers of D coefficients OpenCV takes for it
DISTORTION = {'plumb_bob': (0, 4, 5, 8, 12, 14), 'rational_polynomial': (0, 4, 5, 8, 12, 14),
              'equidistant': (0, 4)}


@dataclass(frozen=True)
class StereoModel:
    fx: float  # the left rectified camera, from P_left
    fy: float
    cx: float
    cy: float
    cx_right: float  # from P_right
    baseline: float  # T, in the unit of P_right[0,3] / P_right[0,0] (metres)

    @property
    def cx_offset(self):
        """cx_left - cx_right: a disparity x_left - x_right minus this is the geometric one."""
        return self.cx - self.cx_right

    def q(self):
        """Return the 4x4 reprojection matrix Q, as image_geometry's (of raw disparities)."""
        tx = -self.baseline
        return np.array([
            [self.fy * tx, 0, 0, -self.fy * self.cx * tx],
            [0, self.fx * tx, 0, -self.fx * self.cy * tx],
            [0, 0, 0, self.fx * self.fy * tx],
            [0, 0, -self.fy, self.fy * self.cx_offset]])

    def depth(self, disparity):
        """
        Return the float32 depth, metres along the optical axis, of a disparity x_l - x_r.

        That is fx * T / (d - cx_offset); NaN where d is NaN (invalid) or d - cx_offset <= 0
        (no finite depth in front of the camera).
        """
        d = disparity - np.float32(self.cx_offset)
        valid = d > 0
        z = np.full(d.shape, np.nan, np.float32)
        np.divide(np.float32(self.fx * self.baseline), d, out=z, where=valid)
        return z

    def points(self, disparity):
        """
        Return the (H, W, 3) float32 points x right, y down, z forward in the left camera.

        These equal OpenCV's reprojectImageTo3D(disparity, self.q()) where the depth is
        valid, and are NaN elsewhere.
        """
        z = self.depth(disparity)
        h, w = z.shape
        x = (np.arange(w, dtype=np.float32) - np.float32(self.cx)) / np.float32(self.fx)
        y = (np.arange(h, dtype=np.float32) - np.float32(self.cy)) / np.float32(self.fy)
        return np.stack(np.broadcast_arrays(x[None, :] * z, y[:, None] * z, z), axis=-1)


def _projection(info, side):
    p = np.asarray(info.p, float).reshape(3, 4)
    if not np.isfinite(p).all():
        raise ValueError(f'{side} camera_info P is not finite: {p.ravel().tolist()}')
    if not (p[0, 0] > 0 and p[1, 1] > 0):
        raise ValueError(f'{side} camera_info has no projection (P[0,0] = {p[0, 0]:g}, '
                         f'P[1,1] = {p[1, 1]:g}): the camera is not calibrated')
    return p


def stereo_model(left_info, right_info, shape, max_disp):
    """
    Return the StereoModel of the two CameraInfos for images of `shape` (H, W[, C]).

    Raises ValueError saying why there is none: a missing camera_info, no projection P
    (uncalibrated), a zero or negative baseline, a size other than the images', a left
    principal point `max_disp` or more px right of the right one (no searched disparity
    would be in front of the cameras), or f or T beyond the float32 fields of
    stereo_msgs/DisparityImage.
    """
    for side, info in (('left', left_info), ('right', right_info)):
        if info is None:
            raise ValueError(f'no {side} camera_info received')
        if info.width and info.height and (info.height, info.width) != tuple(shape[:2]):
            raise ValueError(f'{side} camera_info is for {info.width}x{info.height} images, '
                             f'the images are {shape[1]}x{shape[0]}')
    pl, pr = _projection(left_info, 'left'), _projection(right_info, 'right')
    baseline = -pr[0, 3] / pr[0, 0] + 0.0  # + 0.0: no -0 in the message
    if not baseline > 0:
        raise ValueError(f'baseline T = -P_right[0,3] / P_right[0,0] = {baseline:g} is not '
                         'positive: the right camera_info P[0,3] must be -fx * baseline')
    model = StereoModel(pl[0, 0], pl[1, 1], pl[0, 2], pl[1, 2], pr[0, 2], baseline)
    if not model.cx_offset < max_disp:  # d - cx_offset > 0 for no searched d: no depth
        raise ValueError(f'the left principal point is {model.cx_offset:g} px right of the '
                         f'right one (left cx - right cx), not below max_disparity {max_disp}')
    if not max(model.fx, baseline) <= FLOAT32_MAX:
        raise ValueError(f'f {model.fx:g} or baseline {baseline:g} does not fit the float32 '
                         'fields of stereo_msgs/DisparityImage')
    return model


def camera_model(info, shape, config):
    """
    Return (StereoModel, None) of {side: CameraInfo or None} for `config`, or (None, why).

    `why` is the text: the error itself, with its traceback, would hold the caller's frame
    and all it refers to (the pipeline, its CNN) in a cycle until a garbage collection.
    """
    try:
        return stereo_model(info['left'], info['right'], shape, config.max_disp), None
    except ValueError as err:
        return None, str(err)


def depth_scale(model):
    """Return the pipeline's `camera` (f T, cx_left - cx_right) of a model; None without one."""
    return None if model is None else (model.fx * model.baseline, model.cx_offset)


class Rectifier:
    """
    Rectify raw images with their CameraInfo's K, D, R and P, as image_proc does.

    Bilinear interpolation on OpenCV maps in fixed point; the maps of each side are built
    once per calibration and kept while the CameraInfo stays the same. A misalignment to
    undo folds into the maps (`alignment.fold`, float maps kept while it stays the same), so
    that the image is resampled once.
    """

    def __init__(self):
        self._maps = {}  # side -> (calibration key, map1, map2)
        self._folded = {}  # side -> ((calibration key, misalignment), map_x, map_y)

    def __call__(self, side, info, image, topic='image', misalignment=None):
        """
        Return `image` of `side` rectified; ValueError naming `topic` if `info` cannot.

        `misalignment`: an `alignment.Misalignment` of the rectified image to undo in the
        same remap (None: rectified only).
        """
        h, w = image.shape[:2]
        try:
            if info is None:
                raise ValueError(f'no {side} camera_info received: cannot rectify')
            key = (w, h, info.width, info.height, info.distortion_model, tuple(info.d),
                   tuple(info.k), tuple(info.r), tuple(info.p), info.binning_x, info.binning_y,
                   (info.roi.x_offset, info.roi.y_offset, info.roi.width, info.roi.height))
            if self._maps.get(side, (None,))[0] != key:
                self._maps[side] = (key, *_rectify_maps(side, info, w, h))
        except ValueError as err:
            raise ValueError(f'{topic}: {err}') from None
        key, map1, map2 = self._maps[side]
        if misalignment is not None:
            if self._folded.get(side, (None,))[0] != (key, misalignment):
                plain = cv2.convertMaps(map1, map2, cv2.CV_32FC1)
                self._folded[side] = ((key, misalignment), *fold(misalignment, *plain))
            _, map1, map2 = self._folded[side]
        return cv2.remap(image, map1, map2, cv2.INTER_LINEAR)


def _rectify_maps(side, info, w, h):
    where = f'{side} camera_info'
    if (info.width, info.height) != (w, h):
        raise ValueError(f'{where} is for {info.width}x{info.height} images, '
                         f'the image is {w}x{h}')
    if info.binning_x > 1 or info.binning_y > 1 or info.roi.width or info.roi.height:
        raise ValueError(f'{where}: binning or a region of interest is not supported')
    if info.distortion_model not in DISTORTION:
        raise ValueError(f'{where}: distortion model {info.distortion_model!r} is not '
                         f'supported; expected one of {", ".join(DISTORTION)}')
    k = np.asarray(info.k, float).reshape(3, 3)
    d = np.asarray(info.d, float)
    r = np.asarray(info.r, float).reshape(3, 3)
    p = _projection(info, side)[:, :3]
    if not (np.isfinite(k).all() and np.isfinite(d).all() and np.isfinite(r).all()):
        raise ValueError(f'{where}: K, D or R is not finite')
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        raise ValueError(f'{where}: K has no focal length (K[0,0] = {k[0, 0]:g})')
    if len(d) not in DISTORTION[info.distortion_model]:
        raise ValueError(f'{where}: {len(d)} D coefficients for {info.distortion_model}; '
                         f'expected {" or ".join(map(str, DISTORTION[info.distortion_model]))}')
    if info.distortion_model == 'equidistant':
        d = d if len(d) else np.zeros(4)
        return cv2.fisheye.initUndistortRectifyMap(k, d, r, p, (w, h), cv2.CV_16SC2)
    return cv2.initUndistortRectifyMap(k, d, r, p, (w, h), cv2.CV_16SC2)
