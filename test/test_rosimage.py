"""Image and CompressedImage <-> numpy on a real photo: encodings, formats, bad input."""
import array
from types import SimpleNamespace

import cv2
from gcp_stereo_ros.ros.rosimage import (array_to_compressed_fields, array_to_image_fields,
                                         compressed_to_array, image_to_array, message_to_array)
import numpy as np
import pytest
from skimage import data


@pytest.fixture(scope='module')
def rgb():
    return data.stereo_motorcycle()[0]  # (500, 741, 3) uint8; odd width catches alignment slips


@pytest.fixture(scope='module')
def arrays(rgb):
    gray8 = (rgb @ np.array([0.299, 0.587, 0.114])).astype(np.uint8)
    return {
        'mono8': gray8,
        'mono16': gray8.astype(np.uint16) * 257 + np.arange(741, dtype=np.uint16),
        '32FC1': rgb[:, :, 0].astype(np.float32) / 7.0 - 3.25,
        'rgb8': rgb,
        'bgr8': rgb,
    }


def msg_from(fields, **changes):
    return SimpleNamespace(**{**fields, **changes})


@pytest.mark.parametrize('encoding', ['mono8', 'mono16', '32FC1', 'rgb8', 'bgr8'])
@pytest.mark.parametrize('container', [np.asarray, bytes, bytearray, list,
                                       lambda d: array.array('B', d.tobytes())])
def test_round_trip(arrays, encoding, container):
    a = arrays[encoding]
    fields = array_to_image_fields(a, encoding)
    assert fields['data'].dtype == np.uint8 and fields['data'].ndim == 1
    assert (fields['height'], fields['width'], fields['is_bigendian']) == (500, 741, 0)
    assert fields['step'] == 741 * (a.itemsize * (3 if a.ndim == 3 else 1))
    out = image_to_array(msg_from(fields, data=container(fields['data'])))
    assert out.dtype == a.dtype and out.shape == a.shape
    np.testing.assert_array_equal(out, a)


def test_bgr8_stores_blue_first(rgb):
    fields = array_to_image_fields(rgb, 'bgr8')
    np.testing.assert_array_equal(fields['data'][:3], rgb[0, 0, ::-1])
    fields = array_to_image_fields(rgb, 'rgb8')
    np.testing.assert_array_equal(fields['data'][:3], rgb[0, 0])


@pytest.mark.parametrize('encoding, order', [('rgba8', [0, 1, 2, 3]), ('bgra8', [2, 1, 0, 3])])
def test_alpha_encodings_give_rgb(rgb, encoding, order):
    alpha = np.full(rgb.shape[:2] + (1,), 77, np.uint8)
    stored = np.concatenate([rgb, alpha], axis=2)[:, :, order]
    msg = SimpleNamespace(height=500, width=741, encoding=encoding, is_bigendian=0, step=741 * 4,
                          data=stored.tobytes())
    out = image_to_array(msg)
    assert out.shape == rgb.shape
    np.testing.assert_array_equal(out, rgb)


@pytest.mark.parametrize('encoding', ['mono8', 'mono16', '32FC1', 'rgb8'])
def test_row_padding_is_skipped(arrays, encoding):
    a = arrays[encoding]
    fields = array_to_image_fields(a, encoding)
    row = fields['step']
    step = row + 5  # odd padding: 16/32-bit rows start unaligned
    padded = np.full((fields['height'], step), 0xAB, np.uint8)
    padded[:, :row] = fields['data'].reshape(fields['height'], row)
    out = image_to_array(msg_from(fields, step=step, data=padded.reshape(-1)))
    np.testing.assert_array_equal(out, a)


@pytest.mark.parametrize('encoding', ['mono16', '32FC1'])
def test_big_endian(arrays, encoding):
    a = arrays[encoding]
    big = a.astype(a.dtype.newbyteorder('>'))
    msg = SimpleNamespace(height=500, width=741, encoding=encoding, is_bigendian=1,
                          step=741 * a.itemsize, data=big.tobytes())
    out = image_to_array(msg)
    assert out.dtype == a.dtype and out.dtype.isnative
    np.testing.assert_array_equal(out, a)
    assert not np.array_equal(image_to_array(msg_from(vars(msg), is_bigendian=0)), a)


def test_result_does_not_alias_message_data(arrays):
    fields = array_to_image_fields(arrays['mono8'], 'mono8')
    out = image_to_array(msg_from(fields))
    out[0, 0] ^= 0xFF
    assert fields['data'][0] == arrays['mono8'][0, 0]


def test_fields_do_not_alias_input(arrays):
    a = arrays['mono8'].copy()
    fields = array_to_image_fields(a, 'mono8')
    a[0, 0] ^= 0xFF
    assert fields['data'][0] != a[0, 0]


@pytest.mark.parametrize('change, reason', [
    ({'encoding': 'yuv422'}, "unsupported encoding 'yuv422'"),
    ({'encoding': '16UC1'}, "unsupported encoding '16UC1'"),
    ({'height': 0, 'data': b''}, 'empty'),
    ({'width': 0}, 'empty'),
    ({'step': 741 * 2 - 1}, 'step 1481 is smaller than width'),
    ({'data': b'\0' * (741 * 2 * 500 - 1)}, 'data holds 740999 bytes but step \\* height'),
    ({'data': b'\0' * (741 * 2 * 501)}, 'data holds 742482 bytes'),
])
def test_bad_image_raises(arrays, change, reason):
    fields = array_to_image_fields(arrays['mono16'], 'mono16')
    with pytest.raises(ValueError, match=f'^/cam/left/image_rect: .*{reason}'):
        image_to_array(msg_from(fields, **change), topic='/cam/left/image_rect')


@pytest.mark.parametrize('bad', [np.nan, np.inf, -np.inf])
def test_non_finite_float_image_raises(arrays, bad):
    a = arrays['32FC1'].copy()
    a[123, 456] = bad
    with pytest.raises(ValueError, match='^disparity: 32FC1 image contains NaN or inf'):
        image_to_array(msg_from(array_to_image_fields(a, '32FC1')), topic='disparity')


@pytest.mark.parametrize('value, encoding, reason', [
    (np.zeros((4, 5), np.uint16), 'mono8', 'mono8 needs a uint8 \\(H, W\\) array, got uint16'),
    (np.zeros((4, 5), np.float64), '32FC1', 'needs a float32'),
    (np.zeros((4, 5, 3), np.uint8), 'mono8',
     'needs a uint8 \\(H, W\\) array, got uint8 \\(4, 5, 3\\)'),
    (np.zeros((4, 5), np.uint8), 'rgb8', 'rgb8 needs a uint8 \\(H, W, 3\\)'),
    (np.zeros((4, 5, 4), np.uint8), 'bgr8', 'bgr8 needs a uint8 \\(H, W, 3\\)'),
    (np.zeros((0, 5), np.uint8), 'mono8', 'empty'),
    (np.zeros((4, 5, 4), np.uint8), 'rgba8', "unsupported encoding 'rgba8' for writing"),
])
def test_bad_array_raises(value, encoding, reason):
    with pytest.raises(ValueError, match=reason):
        array_to_image_fields(value, encoding)


@pytest.mark.parametrize('encoding', ['rgb8', 'mono16', '32FC1'])
def test_rclpy_image_round_trip(arrays, encoding):
    from sensor_msgs.msg import Image
    from std_msgs.msg import Header

    a = arrays[encoding]
    fields = array_to_image_fields(a, encoding)
    buf = array.array('B')  # the fast path documented in array_to_image_fields
    buf.frombytes(fields.pop('data'))
    msg = Image(header=Header(frame_id='left'), **fields)
    msg.data = buf
    assert isinstance(msg.data, array.array) and len(msg.data) == msg.step * msg.height
    np.testing.assert_array_equal(image_to_array(msg, topic='left'), a)


@pytest.mark.parametrize('encoding', ['mono8', 'rgb8'])
def test_compressed_round_trip(arrays, encoding):
    a = arrays[encoding]
    png = array_to_compressed_fields(a, 'png')
    assert png['format'] == ('rgb8; png compressed bgr8' if a.ndim == 3 else
                             'mono8; png compressed ')  # as compressed_image_transport writes
    np.testing.assert_array_equal(message_to_array(msg_from(png)), a)  # lossless
    jpeg = array_to_compressed_fields(a, 'jpeg')
    assert jpeg['format'].startswith(f'{encoding}; jpeg compressed ')
    decoded = compressed_to_array(msg_from(jpeg, data=bytes(jpeg['data'])))
    assert decoded.shape == a.shape and decoded.dtype == np.uint8
    assert 0 < np.abs(decoded.astype(int) - a).mean() < 3  # lossy, close


def test_compressed_colour_order_follows_the_format(rgb):
    bgr_png = cv2.imencode('.png', rgb[:, :, ::-1])[1].reshape(-1)
    rgb_png = cv2.imencode('.png', rgb)[1].reshape(-1)
    for fmt, data_ in (('jpeg', bgr_png), ('rgb8; png compressed bgr8', bgr_png),
                       ('rgb8; png compressed rgb8', rgb_png)):  # old publishers: plain 'jpeg'
        np.testing.assert_array_equal(compressed_to_array(msg_from({'format': fmt,
                                                                    'data': data_})), rgb)
    mono16 = np.arange(60 * 80, dtype=np.uint16).reshape(60, 80) * 13
    png16 = cv2.imencode('.png', mono16)[1].reshape(-1)
    np.testing.assert_array_equal(
        compressed_to_array(msg_from({'format': 'mono16; png compressed ', 'data': png16})),
        mono16)


@pytest.mark.parametrize('fmt, data_, reason', [
    ('rgb8; png compressed bgr8', b'', '0 bytes of format'),
    ('rgb8; jpeg compressed bgr8', b'\xff\xd8 truncated', 'do not decode'),
    ('16UC1; compressedDepth png', b'\x00' * 20, 'compressedDepth images are not supported'),
])
def test_compressed_bad_input_names_the_topic(fmt, data_, reason):
    with pytest.raises(ValueError, match=f'^/cam/left/image/compressed: .*{reason}'):
        compressed_to_array(msg_from({'format': fmt, 'data': data_}),
                            '/cam/left/image/compressed')
