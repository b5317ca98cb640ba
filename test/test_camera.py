"""The stereo camera model of two CameraInfos: its checks, Q, and rectification models."""
from types import SimpleNamespace

import cv2
from gcp_stereo_ros.ros.camera import Rectifier, stereo_model
import numpy as np
import pytest

W, H, F = 120, 80, 100.0


def info(p=(F, 0, 60, 0, 0, F, 40, 0, 0, 0, 1, 0), **changes):
    fields = {'width': W, 'height': H, 'distortion_model': 'plumb_bob', 'd': [0.0] * 5,
              'k': [F, 0, 60, 0, F, 40, 0, 0, 1], 'r': [1, 0, 0, 0, 1, 0, 0, 0, 1], 'p': list(p),
              'binning_x': 0, 'binning_y': 0,
              'roi': SimpleNamespace(x_offset=0, y_offset=0, width=0, height=0)}
    return SimpleNamespace(**{**fields, **changes})


def right(tx=-F * 0.1, cx=58):
    return info((F, 0, cx, tx, 0, F, 40, 0, 0, 0, 1, 0))


def test_model_geometry_and_q():
    model = stereo_model(info(), right(), (H, W, 3), 64)
    assert (model.fx, model.baseline, model.cx_offset) == (F, pytest.approx(0.1), 2)
    disp = np.array([[np.nan, 2.0, 2.5, 12.0]], np.float32)
    depth = model.depth(disp)
    assert np.isnan(depth[0, :2]).all()  # invalid, and d - offset = 0: no finite depth
    np.testing.assert_allclose(depth[0, 2:], [F * 0.1 / 0.5, F * 0.1 / 10], rtol=1e-6)
    q = model.q()
    xyzw = q @ np.array([3.0, 5.0, 12.0, 1.0])  # (u, v, raw disparity, 1)
    np.testing.assert_allclose(xyzw[:3] / xyzw[3], model.points(
        np.full((6, 4), 12.0, np.float32))[5, 3], rtol=1e-6)


@pytest.mark.parametrize('left, right_info, reason', [
    (None, right(), 'no left camera_info received'),
    (info(p=[0.0] * 12), right(), 'left camera_info has no projection'),
    (info(), right(tx=0.0), r'baseline T = -P_right\[0,3\] / P_right\[0,0\] = 0 is not positive'),
    (info(), right(tx=F * 0.1), 'baseline T .* = -0.1 is not positive'),
    (info(p=(F, 0, np.nan, 0, 0, F, 40, 0, 0, 0, 1, 0)), right(), 'P is not finite'),
    (info(width=640, height=480), right(), 'for 640x480 images, the images are 120x80'),
    (info(), right(cx=-40), 'left principal point is 100 px right of the right one .* not '
     'below max_disparity 64'),
    (info(p=(1e300, 0, 60, 0, 0, 1e300, 40, 0, 0, 0, 1, 0)),
     info(p=(1e300, 0, 60, -1e299, 0, 1e300, 40, 0, 0, 0, 1, 0)), 'does not fit the float32'),
])
def test_model_says_why_there_is_none(left, right_info, reason):
    with pytest.raises(ValueError, match=reason):
        stereo_model(left, right_info, (H, W), 64)


def test_model_takes_any_right_principal_point_further_right():
    """Middlebury's doffs: cx_right - cx_left > 0 adds to every disparity, all in front."""
    model = stereo_model(info(), right(cx=360), (H, W), 64)
    assert model.cx_offset == -300 and (model.depth(np.float32([[0.0, 63.0]])) > 0).all()


def test_rectifier_models_and_refusals():
    image = np.random.default_rng(0).integers(0, 255, (H, W), np.uint8)
    rectify = Rectifier()
    np.testing.assert_array_equal(rectify('left', info(), image), image)  # identity: unchanged
    fisheye = info(distortion_model='equidistant', d=[0.05, 0.01, 0.0, 0.0])
    k = np.reshape(fisheye.k, (3, 3))
    m1, m2 = cv2.fisheye.initUndistortRectifyMap(k, np.array(fisheye.d), np.eye(3), k, (W, H),
                                                 cv2.CV_16SC2)
    np.testing.assert_array_equal(rectify('left', fisheye, image),
                                  cv2.remap(image, m1, m2, cv2.INTER_LINEAR))
    for bad, reason in ((None, '^image: no left camera_info received: cannot rectify'),
                        (info(distortion_model='fov'), "distortion model 'fov' is not supported"),
                        (info(d=[0.1, 0.2, 0.3]), '3 D coefficients for plumb_bob'),
                        (info(binning_x=2), 'binning'),
                        (info(width=64), 'is for 64x80 images, the image is 120x80'),
                        (info(k=[0.0] * 9), 'K has no focal length')):
        with pytest.raises(ValueError, match=reason):
            rectify('left', bad, image)
