"""Input checks, intensity conversions and resampling shared by every stage."""
import cv2
import numpy as np
import numpy.typing as npt

# ITU-R BT.601 luma, as cv2.cvtColor and Pillow's convert('L') use.
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def to_gray(image: npt.ArrayLike, name: str = 'image') -> npt.NDArray[np.float32]:
    """
    Return `image` as a float32 (H, W) gray array.

    Accepts uint8, uint16 or float arrays, gray (H, W) or (H, W, 1), RGB (H, W, 3) or
    RGBA (H, W, 4, alpha ignored). Channel order is RGB; convert BGR before calling.
    Raises ValueError naming `name` for anything else, including NaN or inf values.
    """
    a = np.asarray(image)
    if a.dtype == np.bool_ or not (np.issubdtype(a.dtype, np.integer)
                                   or np.issubdtype(a.dtype, np.floating)):
        raise ValueError(f'{name}: unsupported dtype {a.dtype}; expected uint8, uint16 or float')
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = a[:, :, :3].astype(np.float32) @ _LUMA
    elif a.ndim != 2:
        raise ValueError(f'{name}: expected a gray (H, W) or RGB (H, W, 3) image, '
                         f'got shape {a.shape}')
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f'{name}: empty image of shape {a.shape}')
    a = np.ascontiguousarray(a, dtype=np.float32)
    if not np.isfinite(a).all():
        raise ValueError(f'{name}: contains NaN or inf values')
    return a


def gray_pair(left: npt.ArrayLike, right: npt.ArrayLike
              ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """Both images as float32 gray; raises ValueError unless they have the same size."""
    lg, rg = to_gray(left, 'left image'), to_gray(right, 'right image')
    if lg.shape != rg.shape:
        raise ValueError(f'left image is {lg.shape[1]}x{lg.shape[0]} but right image is '
                         f'{rg.shape[1]}x{rg.shape[0]} (width x height); '
                         'a rectified pair has one size')
    return lg, rg


def mean_std(gray: npt.ArrayLike) -> tuple[float, float]:
    """Return the mean and the std (1 for a flat image) that `standardize` uses."""
    g = np.asarray(gray, dtype=np.float32)
    std = float(g.std())
    return float(g.mean()), (std if std > 1e-6 else 1.0)


def standardize(gray: npt.ArrayLike) -> np.ndarray:
    """Per-image normalization of the paper: subtract the mean, divide by the std."""
    mean, std = mean_std(gray)
    return (np.asarray(gray, dtype=np.float32) - mean) / std


def bin_area(gray: np.ndarray, factor: int) -> np.ndarray:
    """
    Return the mean of each `factor` x `factor` block of a float32 gray image.

    Rows and columns past the last whole block are left out; ValueError if no block fits.
    """
    h, w = gray.shape[0] // factor, gray.shape[1] // factor
    if h == 0 or w == 0:
        raise ValueError(f'a {gray.shape[1]}x{gray.shape[0]} image holds no {factor}x{factor} '
                         f'block to bin (downsample {factor})')
    return cv2.resize(gray[:h * factor, :w * factor], (w, h), interpolation=cv2.INTER_AREA)


def upsample(a: np.ndarray, factor: int, shape: tuple[int, ...]) -> np.ndarray:
    """
    Return `a` blown up to `shape` (H, W): each pixel repeated `factor` x `factor` times.

    The rows and columns that `bin_area` left out repeat the last ones.
    """
    rows = np.minimum(np.arange(shape[0]) // factor, a.shape[0] - 1)
    cols = np.minimum(np.arange(shape[1]) // factor, a.shape[1] - 1)
    return np.take(np.take(a, rows, axis=0), cols, axis=1)


def subsample(a: npt.ArrayLike, factor: int, shape: tuple[int, ...]) -> np.ndarray:
    """Return the (H, W) grid `shape` of which `a` is the `upsample` by `factor` (its inverse)."""
    return np.asarray(a)[:shape[0] * factor:factor, :shape[1] * factor:factor]


def mask_image(mask: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    """Boolean mask as a uint8 0/255 image (mono8, PNG)."""
    return np.asarray(mask, dtype=bool).astype(np.uint8) * 255
