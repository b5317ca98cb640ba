"""
sensor_msgs/Image and CompressedImage <-> numpy without cv_bridge, image_transport or rclpy.

Works on any object with the Image fields (height, width, encoding, is_bigendian, step,
data) or the CompressedImage ones (format, data): rclpy messages (data is array.array('B'))
as well as rosbags ones (numpy uint8).
"""
import cv2
import numpy as np

# encoding: (little-endian dtype of one channel, channels)
_READ = {
    'mono8': ('u1', 1), 'mono16': ('<u2', 1), '32FC1': ('<f4', 1),
    'rgb8': ('u1', 3), 'bgr8': ('u1', 3), 'rgba8': ('u1', 4), 'bgra8': ('u1', 4),
}
_WRITE = ('mono8', 'mono16', '32FC1', 'rgb8', 'bgr8')


def image_to_array(msg, topic='image'):
    """
    Return the image of `msg` as a new numpy array.

    mono8, mono16 and 32FC1 give (H, W) uint8, uint16 or float32; rgb8, bgr8, rgba8 and
    bgra8 give (H, W, 3) uint8 in RGB order (alpha dropped). Row padding (`step`) and
    `is_bigendian` are honoured. Raises ValueError naming `topic` for an unsupported
    encoding, an empty image, a step or data size that does not fit, or NaN/inf floats.
    """
    encoding = msg.encoding
    if encoding not in _READ:
        raise ValueError(f'{topic}: unsupported encoding {encoding!r}; '
                         f'expected one of {", ".join(_READ)}')
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height == 0 or width == 0:
        raise ValueError(f'{topic}: empty {encoding} image of {width}x{height} pixels')
    dtype, channels = _READ[encoding]
    dtype = np.dtype(dtype)
    row_bytes = width * channels * dtype.itemsize
    if step < row_bytes:
        raise ValueError(f'{topic}: step {step} is smaller than width * bytes per pixel = '
                         f'{width} * {channels * dtype.itemsize} = {row_bytes}')
    data = msg.data
    if isinstance(data, (list, tuple)):
        raw = np.asarray(data, dtype=np.uint8)
    else:
        raw = np.frombuffer(data, np.uint8)  # bytes, bytearray, array.array or numpy: no copy
    if raw.size != step * height:
        raise ValueError(f'{topic}: data holds {raw.size} bytes but step * height = '
                         f'{step} * {height} = {step * height}')
    if msg.is_bigendian:
        dtype = dtype.newbyteorder('>')
    pixels = raw.reshape(height, step)[:, :row_bytes].view(dtype)
    if channels > 1:
        pixels = pixels.reshape(height, width, channels)
        pixels = pixels[:, :, 2::-1] if encoding.startswith('bgr') else pixels[:, :, :3]
    image = np.array(pixels, dtype=dtype.newbyteorder('='), order='C')
    if image.dtype.kind == 'f' and not np.isfinite(image).all():
        raise ValueError(f'{topic}: {encoding} image contains NaN or inf values')
    return image


def array_to_image_fields(array, encoding):
    """
    Return the Image fields (all but header) for `array`.

    The fields are height, width, encoding, is_bigendian=0, step and data.

    `array` is uint8 (H, W) for mono8, uint16 (H, W) for mono16, float32 (H, W) for 32FC1
    and uint8 (H, W, 3) in RGB order for rgb8 or bgr8 (reordered here). `data` is a new
    1-D numpy uint8 array, which is what rosbags' Image takes: `Image(header=h, **fields)`.

    rclpy's Image must not get the numpy array: it copies it element by element. Fastest
    (1-2 memcpys), with the standard-library module `array`:
        buf = array.array('B'); buf.frombytes(fields.pop('data'))
        msg = Image(header=h, **fields); msg.data = buf
    `Image(header=h, **dict(fields, data=fields['data'].tobytes()))` copies once more and is
    fine too, but never assign bytes to `msg.data`: with ROS_PYTHON_CHECK_FIELDS=1 rclpy
    checks every byte in Python; an array.array('B') skips that check (timings:
    doc/notes/implementation_history.md).
    """
    if encoding not in _WRITE:
        raise ValueError(f'unsupported encoding {encoding!r} for writing; '
                         f'expected one of {", ".join(_WRITE)}')
    dtype, channels = _READ[encoding]
    dtype = np.dtype(dtype)
    a = np.asarray(array)
    native = dtype.newbyteorder('=')
    if (a.dtype != native or a.ndim != (2 if channels == 1 else 3)
            or (channels > 1 and a.shape[2] != 3)):
        shape = '(H, W)' if channels == 1 else '(H, W, 3)'
        raise ValueError(f'{encoding} needs a {native} {shape} array, got {a.dtype} {a.shape}')
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f'{encoding}: empty array of shape {a.shape}')
    if encoding == 'bgr8':
        a = a[:, :, ::-1]
    height, width = a.shape[:2]
    return {
        'height': height, 'width': width, 'encoding': encoding, 'is_bigendian': 0,
        'step': width * channels * dtype.itemsize,
        'data': np.array(a, dtype=dtype, order='C').reshape(-1).view(np.uint8),
    }


def image_message(types, header, array, encoding, data=np.asarray):
    """
    Return a sensor_msgs/Image of `array` in `encoding`, as `array_to_image_fields` takes them.

    `types.Image` is the message class (rclpy's or rosbags'); `data` converts the uint8
    numpy buffer to what it wants (array.array('B') for rclpy, as is for rosbags).
    """
    fields = array_to_image_fields(array, encoding)
    fields['data'] = data(fields['data'])
    return types.Image(header=header, **fields)


def message_to_array(msg, topic='image'):
    """Return the image of a sensor_msgs/Image or CompressedImage as a new numpy array."""
    if hasattr(msg, 'format'):
        return compressed_to_array(msg, topic)
    return image_to_array(msg, topic)


def compressed_to_array(msg, topic='image/compressed'):
    """
    Return the image of a sensor_msgs/CompressedImage (jpeg or png) as a new numpy array.

    As image_transport's compressed subscriber reads it: `format` is '<encoding>; <jpeg|png>
    compressed <bgr8|mono8|...>' (or just 'jpeg' from old publishers, colour then in BGR
    order). Gives what `image_to_array` gives for the original encoding: (H, W) uint8 or
    uint16 gray, or (H, W, 3) uint8 RGB. Raises ValueError naming `topic` for data that does
    not decode, or a format this node does not read (compressedDepth, colour beyond 8 bits).
    """
    fmt = msg.format
    if 'compressedDepth' in fmt:
        raise ValueError(f'{topic}: format {fmt!r}: compressedDepth images are not supported')
    data = msg.data
    raw = (np.asarray(data, np.uint8) if isinstance(data, (list, tuple))
           else np.frombuffer(data, np.uint8))
    image = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED) if raw.size else None
    if image is None:
        raise ValueError(f'{topic}: {raw.size} bytes of format {fmt!r} do not decode as an '
                         'image (jpeg or png expected)')
    if image.ndim == 2:
        return image
    if image.dtype != np.uint8:
        raise ValueError(f'{topic}: format {fmt!r}: {image.dtype} colour images are not '
                         'supported; expected 8-bit colour or gray')
    compressed = fmt.partition(';')[2]
    bgr = 'compressed bgr' in compressed if compressed else True  # old publishers: BGR
    return np.ascontiguousarray(image[:, :, 2::-1] if bgr else image[:, :, :3])


def array_to_compressed_fields(array, fmt):
    """
    Return the CompressedImage fields (all but header) for `array`, as image_transport writes.

    `array` is uint8 (H, W) gray or (H, W, 3) RGB; `fmt` is 'png' (lossless) or 'jpeg'
    (quality 95). `format` follows compressed_image_transport, e.g. 'rgb8; png compressed
    bgr8'; `data` is a 1-D numpy uint8 array.
    """
    if fmt not in ('png', 'jpeg'):
        raise ValueError(f"compressed format must be 'png' or 'jpeg', got {fmt!r}")
    a = np.asarray(array)
    if a.dtype != np.uint8 or not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
        raise ValueError(f'compressing needs a uint8 (H, W) or (H, W, 3) array, '
                         f'got {a.dtype} {a.shape}')
    color = a.ndim == 3
    ok, data = cv2.imencode('.png' if fmt == 'png' else '.jpg', a[:, :, ::-1] if color else a,
                            [] if fmt == 'png' else [cv2.IMWRITE_JPEG_QUALITY, 95])
    if not ok:
        raise ValueError(f'OpenCV could not encode a {a.shape} image as {fmt}')
    encoding = 'rgb8' if color else 'mono8'
    target = 'bgr8' if color else ('mono8' if fmt == 'jpeg' else '')
    return {'format': f'{encoding}; {fmt} compressed {target}', 'data': data.reshape(-1)}
