"""
The pipeline's memory: its volumes' number type, a bound of a pair's need, the allocator.

`memory_bytes` bounds what a pair needs (checked against memory_limit_mb before anything is
allocated); `mmap_large_arrays` sets glibc's allocator as long-running processes use it.
"""
import ctypes
from typing import Callable

import numpy as np

from .cnn.filter import scratch_size
from .config import DOWNSAMPLE, StereoConfig
from .cost import max_cost, UINT16_MAX
from .costs import cost_spec
from .sgm import directions, path_sum_bound

MIB = 1 << 20


def fixed_point_scale(cfg: StereoConfig) -> int | None:
    """
    Return the smallest integer s that allows fixed-point uint16 volumes, or None.

    s makes s * (Census costs, P1, P2, and C_hi, C_low with GCPs) integers whose path sums,
    at most paths * s * (max cost + P2), fit in uint16 (s = 10 for the paper's C_low = 1.3);
    None for a cost that is not integer (SAD: `CostSpec.integer`), or values such as
    C_low = 1.2345, which would need s = 2000. With an s
    the pipeline keeps its volumes in uint16: half the memory, faster SGM, exact integer
    arithmetic; the disparities equal the float32 path's except where float32 rounding of a
    fractional value breaks a tie.
    """
    if not cost_spec(cfg.cost).integer:
        return None
    values = (cfg.p1, cfg.p2) + ((cfg.c_hi, cfg.c_low) if cfg.use_gcp else ())
    top = max(max_cost(cfg.cost, cfg.window), cfg.c_hi if cfg.use_gcp else 0)
    for s in range(1, int(UINT16_MAX // path_sum_bound(cfg.paths, top, cfg.p2)) + 1):
        if all(abs(v * s - round(v * s)) <= 1e-9 * max(1.0, v * s) for v in values):
            return s
    return None


def volume_arithmetic(cfg: StereoConfig
                      ) -> tuple[int | None, np.dtype, Callable[[float], float]]:
    """
    Return (scale, dtype, fixed) of the pipeline's volumes for `cfg`.

    `fixed_point_scale` (None for float32), the volume type (uint16 with a scale, else
    float32), and the map of a cost-unit parameter (P1, P2, C_hi, C_low) into the volume's.
    """
    scale = fixed_point_scale(cfg)
    if scale is None:
        return None, np.dtype(np.float32), lambda v: v
    return scale, np.dtype(np.uint16), lambda v: round(v * scale)


# Bytes per matched pixel besides the volumes, alive at once while the cost volume is built
# (the gray pair 8, the CNN outputs 12, the Census bit strings 48), rounded up; it covers
# the later stages too.
PIXEL_BYTES = 80
# While the CNN runs: the gray pair, its network input and the CNN outputs (8 + 8 + 12 bytes
# per pixel), and of one strip eight layer outputs' worth: a layer's input and output, the
# descriptors copied out, oneDNN's scratchpad (which it keeps for the largest so far), and
# four for the heap, which keeps the blocks freed within a pair for reuse
# (mmap_large_arrays) rather than unmapping them, so where a new block lands varies.
CNN_PIXEL_BYTES = 28
# With cnn_filter_radius, per pixel while the CNN runs: the guide, its window means and
# variance and their temporaries (cnn_filter.guide_stats), float32.
GUIDE_PIXEL_BYTES = 32
STRIP_LAYERS = 8
# With downsample > 1, per full-size pixel: the gray pair (8), the outputs blown up (17),
# rounded up.
FULL_PIXEL_BYTES = 32
# The invalidation and the confidence, per full-size pixel, while the volumes are kept: the
# outputs alive then (35, plain SGM's disparity for plain_check included) and the features
# and their fit (121; the invalidation after them, with background_ratio, 35).
POST_PIXEL_BYTES = 156


def memory_bytes(cfg: StereoConfig, height: int, width: int) -> int:
    """
    Return an upper bound of the memory the pipeline allocates for a pair of this size.

    At the matching resolution (H/downsample x W/downsample, D = matched_disp): the cost and
    path-sum volumes (H x W x D each, kept between frames) and the SGM sweep buffers (3 rows
    of each path from above, W x D each), with `cnn_filter_radius` the CNN filter's rows of
    the volume (`cnn.filter.scratch_size`, kept as well), plus whichever needs more:
    the CNN's arrays with one strip's activations (two images, 64 float32 maps of
    STRIP_ROWS + 8 rows), or
    PIXEL_BYTES per pixel for the later stages; with downsample, FULL_PIXEL_BYTES per
    full-size pixel; or, if more, POST_PIXEL_BYTES per full-size pixel for the invalidation
    and confidence. Measured peaks stay below it (doc/failures.md).
    """
    fixed, per_disparity = _memory_terms(cfg, height, width)
    return fixed + per_disparity * cfg.matched_disp


def _memory_terms(cfg: StereoConfig, height: int, width: int) -> tuple[int, int]:
    """Return (bytes, bytes per matched disparity) of `memory_bytes`."""
    f = cfg.downsample
    h, w = height // f, width // f
    itemsize = volume_arithmetic(cfg)[1].itemsize
    sweep_rows = 3 * sum(dy > 0 for _, dy in directions(cfg.paths))
    per_disparity = (2 * h + sweep_rows) * w * itemsize
    fixed = PIXEL_BYTES * h * w
    if cfg.use_gcp:
        from .cnn.network import FEATURES, PAD, STRIP_ROWS
        strip = 2 * FEATURES * (min(STRIP_ROWS, h) + 2 * PAD) * (w + 2 * PAD) * 4
        pixel = CNN_PIXEL_BYTES + (GUIDE_PIXEL_BYTES if cfg.matched_radius else 0)
        fixed = max(fixed, pixel * h * w + STRIP_LAYERS * strip)
        if cfg.matched_radius:  # cnn_filter.StripFilter's rows, kept as the volumes are
            per_disparity += 4 * scratch_size(h, w, 1, cfg.matched_radius, STRIP_ROWS)
    if f > 1:
        fixed += FULL_PIXEL_BYTES * height * width
    return max(fixed, POST_PIXEL_BYTES * height * width), per_disparity


def check_memory(cfg: StereoConfig, height: int, width: int) -> None:
    """Raise ValueError if a pair of this size needs more than cfg.memory_limit_mb."""
    fixed, per_disparity = _memory_terms(cfg, height, width)
    need = fixed + per_disparity * cfg.matched_disp  # memory_bytes, from the same terms
    if need <= cfg.memory_limit_mb * MIB:
        return
    fits = (cfg.memory_limit_mb * MIB - fixed) // per_disparity * cfg.downsample
    f, nd = cfg.downsample, cfg.matched_disp
    changes = ([f'lower max_disparity (at most {fits} fits)'] if fits >= 1 else []) + (
        ['raise downsample'] if f < max(DOWNSAMPLE) else []) + ['raise memory_limit_mb']
    what = ', '.join(changes[:-1]) + ', or ' + changes[-1] if len(changes) > 1 else changes[0]
    raise ValueError(
        f'{width}x{height} at max_disparity {cfg.max_disp}'
        + (f', downsample {f},' if f > 1 else '')
        + f' needs about {need / MIB:.0f} MB (two {width // f}x{height // f}x{nd} '
        f'{volume_arithmetic(cfg)[1]} volumes), over memory_limit_mb {cfg.memory_limit_mb}: '
        + what)


# Blocks from this size on are mmap'd (`mmap_large_arrays`): above every block a KITTI-size
# frame allocates and frees while it runs (a CNN strip's layer output: 23 MB).
MMAP_BYTES = 64 * MIB


def call_glibc(call: str, *args: int) -> None:
    """Call glibc's `call` (mallopt, malloc_trim); no-op without glibc."""
    try:
        getattr(ctypes.CDLL(None), call)(*args)
    except (OSError, AttributeError):
        pass


def mmap_large_arrays() -> None:
    """
    Make glibc's malloc serve blocks of MMAP_BYTES or more with mmap, in this whole process.

    For long-running processes (the node, the bag tool), with `StereoPipeline.release` at
    idle. glibc's default raises its mmap threshold up to 32 MiB after a large block is
    freed and keeps freed blocks below it in its heaps; a fixed threshold of MMAP_BYTES keeps
    the blocks freed within a pair (a CNN strip's layer outputs) for reuse within it, mmaps
    the volumes, and each pair ends by giving the freed heap memory back (malloc_trim), so
    RSS between pairs follows the arrays alive (measured: doc/notes/implementation_history.md).
    """
    call_glibc('mallopt', -3, MMAP_BYTES)  # M_MMAP_THRESHOLD
