"""
Stereo pairs with ground truth from the standard benchmark layouts (KITTI, Middlebury).

`source` is the word `motorcycle` (scikit-image's Middlebury 2014 pair) or a folder that
is searched recursively for every supported layout. Frame names are scene paths relative
to `source` (its basename when `source` is the scene itself), plus `/<image id>` for KITTI.
"""
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
import functools
import os
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from skimage.data import stereo_motorcycle

LAYOUTS = ('KITTI 2012 (training/image_0, image_1, disp_noc or disp_occ)',
           'KITTI 2015 (training/image_2, image_3, disp_noc_0 or disp_occ_0)',
           'Middlebury v2 (imL.png, imR.png, groundtruth.png, nonocc.png, info.txt)',
           'Middlebury 2003 (im2.png, im6.png, disp2.png)',
           'Middlebury 2006 (view1.png, view5.png, disp1.png)',
           'Middlebury 2014 MiddEval3 / ETH3D two-view (im0.png, im1.png, disp0GT.pfm)',
           'OpenCV-doc Aloe (<name>L.*, <name>R.*, <name>GT.png)')

# (left dir, right dir, (non-occluded GT dir, all-pixels GT dir), left camera, right camera)
# of the KITTI training folder. A frame is scored on its non-occluded GT when it has one.
_KITTI = (('image_0', 'image_1', ('disp_noc', 'disp_occ'), 0, 1),
          ('image_2', 'image_3', ('disp_noc_0', 'disp_occ_0'), 2, 3))
_KITTI_MAX_DISP = 128
Source = str | Path  # 'motorcycle' or a folder
Loaders = dict[str, Callable[[], 'Frame']]


@dataclass
class Frame:
    """One rectified pair; disparities are in pixels of these images, NaN where unknown."""

    name: str
    left: np.ndarray
    right: np.ndarray
    gt: np.ndarray | None
    valid: np.ndarray | None
    max_disp: int
    gt_right: np.ndarray | None = None
    focal_px: float | None = None
    baseline_m: float | None = None
    # (cx, cy) of the left camera; None = the image centre
    principal_px: tuple[float, float] | None = None
    doffs_px: float = 0.0  # right cx - left cx (Middlebury's doffs): depth = f B / (d + doffs)
    # How the scoring departs from the benchmark's own, for reports (e.g. occluded pixels
    # included because the frame has no non-occluded ground truth); None when it does not.
    note: str | None = None


def list_frames(source: Source) -> list[str]:
    """Names of every frame under `source`, sorted."""
    return list(_scan(source))


def load_frame(source: Source, name: str) -> Frame:
    """Return the frame called `name` (as returned by `list_frames(source)`)."""
    frames = _scan(source)
    if name not in frames:
        raise ValueError(f'no frame {name!r} in {source}; available: {", ".join(frames)}')
    return frames[name]()


def load_frames(source: Source, names: Iterable[str] | None = None) -> Iterator[Frame]:
    """Yield the frames `names` (default: all of them) one at a time."""
    frames = _scan(source)
    for name in list(frames) if names is None else names:
        if name not in frames:
            raise ValueError(f'no frame {name!r} in {source}; available: {", ".join(frames)}')
        yield frames[name]()


def _scan(source: Source) -> Loaders:
    """Ordered {name: loader} of every frame under `source`."""
    if str(source) == 'motorcycle':
        return {'motorcycle': _motorcycle}
    root = Path(source)
    if not root.is_dir():
        raise ValueError(f'{source}: not "motorcycle" nor an existing folder')
    frames: Loaders = {}
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        folder = Path(dirpath)
        rel = root.name if folder == root else folder.relative_to(root).as_posix()
        found = _scene(folder, rel, set(filenames))
        if found:
            frames.update(found)
            dirnames.clear()
    if not frames:
        raise ValueError(f'{source}: no stereo pairs found; looked for ' + '; '.join(LAYOUTS))
    return frames


def _scene(folder: Path, rel: str, files: set[str]) -> Loaders:
    """{name: loader} for `folder` if it is a scene of a supported layout, else {}."""
    for training in (folder / 'training', folder):
        for kind in _KITTI:
            left, right, gt_dirs = kind[:3]
            if ((training / left).is_dir() and (training / right).is_dir()
                    and any((training / d).is_dir() for d in gt_dirs)):
                frames: Loaders = {}
                for image in sorted((training / left).glob('*_10.png')):
                    gt = next((training / d / image.name for d in gt_dirs
                               if (training / d / image.name).is_file()), None)
                    if gt is not None:  # frames without ground truth are not listed
                        name = f'{rel}/{image.stem}'
                        frames[name] = functools.partial(_kitti, training, name, image.stem,
                                                         kind, gt)
                return frames
    if {'imL.png', 'imR.png', 'groundtruth.png', 'nonocc.png', 'info.txt'} <= files:
        return {rel: functools.partial(_middlebury_v2, folder, rel)}
    if {'im2.png', 'im6.png', 'disp2.png'} <= files:
        return {rel: functools.partial(_middlebury_pair, folder, rel, 'im2', 'im6', 'disp2',
                                       'disp6', None)}
    if {'view1.png', 'view5.png', 'disp1.png'} <= files:
        parts = [p.lower() for p in folder.resolve().parts]
        scale = 2 if 'halfsize' in parts else 3 if 'thirdsize' in parts else 1
        return {rel: functools.partial(_middlebury_pair, folder, rel, 'view1', 'view5', 'disp1',
                                       'disp5', scale)}
    if {'im0.png', 'im1.png', 'disp0GT.pfm'} <= files:
        return {rel: functools.partial(_middeval3, folder, rel)}
    gts = sorted(f for f in files if f.endswith('GT.png'))
    if gts:
        if len(gts) > 1:
            raise ValueError(f'{folder}: several <name>GT.png files {gts}; '
                             'expected one pair per folder')
        prefix = gts[0][:-len('GT.png')]
        lefts = sorted(f for f in files if f.startswith(prefix + 'L.'))
        rights = sorted(f for f in files if f.startswith(prefix + 'R.'))
        if lefts and rights:
            return {rel: functools.partial(_aloe, folder, rel, lefts[0], rights[0], gts[0])}
    return {}


def _image(path: Path) -> np.ndarray:
    """uint8 gray (H, W) if stored gray, else RGB (H, W, 3)."""
    im = Image.open(path)
    return np.array(im if im.mode == 'L' else im.convert('RGB'))


def _gray8(path: Path) -> np.ndarray:
    """8-bit values; palette PNGs are mapped through their palette."""
    return np.array(Image.open(path).convert('L'))


def _pfm(path: Path) -> np.ndarray:
    """float32 disparity of a one-channel PFM file (rows stored bottom first); inf -> NaN."""
    with open(path, 'rb') as f:
        try:
            kind = f.readline().strip()
            width, height = (int(v) for v in f.readline().split())
            scale = float(f.readline())
        except ValueError:
            kind = None
        if kind != b'Pf':
            raise ValueError(f'{path}: not a one-channel PFM file (Pf, width height, scale)')
        data = np.frombuffer(f.read(), '<f4' if scale < 0 else '>f4')
    if data.size != width * height:
        raise ValueError(f'{path}: {data.size} values for a {width}x{height} PFM image')
    d = np.ascontiguousarray(np.flipud(data.reshape(height, width)), dtype=np.float32)
    d[~np.isfinite(d)] = np.nan
    return d


def _disparity(raw: np.ndarray, scale: float) -> np.ndarray:
    """float32 disparity from stored values; 0 = unknown becomes NaN."""
    d = raw.astype(np.float32) / scale
    d[raw == 0] = np.nan
    return d


def _above(gt: np.ndarray) -> int:
    """Smallest multiple of 16 strictly above the largest known disparity."""
    return 16 * (int(np.nanmax(gt)) // 16 + 1)


def _up16(ndisp: int) -> int:
    """Round a dataset's number of disparities up to a multiple of 16."""
    return -(-ndisp // 16) * 16


def _frame(name: str, left: np.ndarray, right: np.ndarray, gt: np.ndarray, max_disp: int,
           mask: np.ndarray | None = None, gt_right: np.ndarray | None = None,
           **extra: Any) -> Frame:
    """Check the shapes; pixels scored (`valid`) have ground truth and are in `mask`, if any."""
    for what, a in (('right image', right), ('ground truth', gt), ('mask', mask),
                    ('right ground truth', gt_right)):
        if a is not None and a.shape[:2] != left.shape[:2]:
            raise ValueError(f'{name}: {what} is {a.shape[:2]} '
                             f'but left image is {left.shape[:2]}')
    valid = np.isfinite(gt) if mask is None else np.isfinite(gt) & mask
    return Frame(name, left, right, gt, valid, max_disp, gt_right, **extra)


def _motorcycle() -> Frame:
    left, right, gt = stereo_motorcycle()
    gt = np.where(np.isfinite(gt), gt, np.nan).astype(np.float32)
    # The calibration of these down-sampled images, as stereo_motorcycle's docstring gives it.
    return _frame('motorcycle', left, right, gt, 64, focal_px=994.978, baseline_m=0.193001,
                  principal_px=(311.193, 254.877), doffs_px=31.086)


def _kitti(training: Path, name: str, stem: str, kind: tuple[Any, ...], gt_path: Path) -> Frame:
    left, right, (noc, _), *cams = kind
    gt = _disparity(np.array(Image.open(gt_path)), 256.0)
    calib = _kitti_calib(training, stem.split('_')[0], cams)
    occ = gt_path.parent.name
    return _frame(name, _image(training / left / f'{stem}.png'),
                  _image(training / right / f'{stem}.png'), gt, _KITTI_MAX_DISP, **calib,
                  note=None if occ == noc else f'scored on {occ} (occluded pixels included): '
                                               f'no {noc}/{stem}.png')


def _kitti_calib(training: Path, frame_id: str, cams: list[int]) -> dict[str, Any]:
    """
    Return the Frame fields of the two cameras' projection matrices, if shipped, else {}.

    focal_px, baseline_m, principal_px and doffs_px.
    """
    for path, key in ((training / 'calib' / f'{frame_id}.txt', 'P{}'),
                      (training / 'calib_cam_to_cam' / f'{frame_id}.txt', 'P_rect_0{}')):
        if path.is_file():
            rows = dict(line.split(':', 1)
                        for line in path.read_text().splitlines() if ':' in line)
            pl, pr = (np.array(rows[key.format(c)].split(), dtype=float).reshape(3, 4)
                      for c in cams)
            return {'focal_px': float(pr[0, 0]),
                    'baseline_m': float((pl[0, 3] - pr[0, 3]) / pr[0, 0]),
                    'principal_px': (float(pl[0, 2]), float(pl[1, 2])),
                    'doffs_px': float(pr[0, 2] - pl[0, 2])}
    return {}


def _middlebury_v2(folder: Path, name: str) -> Frame:
    lines = (folder / 'info.txt').read_text().split()
    if len(lines) < 2:
        raise ValueError(f'{folder / "info.txt"}: '
                         'expected the scale and the number of disparities')
    scale, ndisp = float(lines[0]), int(lines[1])
    gt = _disparity(_gray8(folder / 'groundtruth.png'), scale)
    return _frame(name, _image(folder / 'imL.png'), _image(folder / 'imR.png'), gt, _up16(ndisp),
                  mask=_gray8(folder / 'nonocc.png') == 255)


def _middlebury_pair(folder: Path, name: str, left: str, right: str, gt_left: str,
                     gt_right: str, scale: int | None) -> Frame:
    """2003 (scale from the width: 1800 px = full size) and 2006 (scale given) scenes."""
    image = _image(folder / f'{left}.png')
    scale = scale or round(1800 / image.shape[1])
    gt = _disparity(_gray8(folder / f'{gt_left}.png'), scale)
    path = folder / f'{gt_right}.png'
    gt_r = _disparity(_gray8(path), scale) if path.is_file() else None
    return _frame(name, image, _image(folder / f'{right}.png'), gt, _above(gt), gt_right=gt_r)


def _middeval3(folder: Path, name: str) -> Frame:
    """
    Middlebury 2014 (MiddEval3) and ETH3D two-view scenes.

    Scored on mask0nocc.png == 255 (non-occluded) when present; max_disp is calib.txt's ndisp
    rounded up to a multiple of 16, or from the ground truth without one; the cameras'
    calibration from calib.txt too, where it has it.
    """
    gt = _pfm(folder / 'disp0GT.pfm')
    mask_path, gt_r = folder / 'mask0nocc.png', folder / 'disp1GT.pfm'
    mask = _gray8(mask_path) == 255 if mask_path.is_file() else None
    ndisp, calibration = _calib_txt(folder / 'calib.txt')
    notes = ([] if mask is not None else
             ['no mask0nocc.png: scored on every pixel with ground truth, occluded ones included'])
    if ndisp is None:
        notes.append('no ndisp in calib.txt: max_disp from the largest ground-truth disparity')
    return _frame(name, _image(folder / 'im0.png'), _image(folder / 'im1.png'), gt,
                  _above(gt) if ndisp is None else _up16(ndisp), mask=mask,
                  gt_right=_pfm(gt_r) if gt_r.is_file() else None, note='; '.join(notes) or None,
                  **calibration)


def _calib_txt(path: Path) -> tuple[int | None, dict[str, Any]]:
    """
    Return (ndisp, calibration) of a Middlebury or ETH3D calib.txt.

    ndisp: `ndisp=`, None without the file or the key. calibration: the Frame fields
    focal_px, baseline_m, principal_px, doffs_px from `cam0=`, `cam1=` (3x3 matrices as
    `[f 0 cx; 0 f cy; 0 0 1]`) and `baseline=` (mm), or {} without them.
    """
    lines = path.read_text().splitlines() if path.is_file() else []
    keys = {key.strip(): value.strip()
            for key, _, value in (line.partition('=') for line in lines)}
    try:
        ndisp = int(keys['ndisp']) if 'ndisp' in keys else None
    except ValueError:
        raise ValueError(f'{path}: ndisp={keys["ndisp"]} is not an integer') from None
    if not {'cam0', 'cam1', 'baseline'} <= keys.keys():
        return ndisp, {}
    try:
        k0, k1 = (np.array(keys[c].strip('[]').replace(';', ' ').split(), float).reshape(3, 3)
                  for c in ('cam0', 'cam1'))
        baseline = float(keys['baseline']) / 1000
    except ValueError:
        raise ValueError(f'{path}: cam0, cam1 or baseline is not a 3x3 matrix or a number '
                         f'({keys["cam0"]!r}, {keys["cam1"]!r}, {keys["baseline"]!r})') from None
    return ndisp, {'focal_px': float(k0[0, 0]), 'baseline_m': baseline,
                   'principal_px': (float(k0[0, 2]), float(k0[1, 2])),
                   'doffs_px': float(k1[0, 2] - k0[0, 2])}


def _aloe(folder: Path, name: str, left: str, right: str, gt: str) -> Frame:
    disp = _disparity(_gray8(folder / gt), 1.0)
    return _frame(name, _image(folder / left), _image(folder / right), disp, _above(disp))
