"""
gcp-stereo-bench: stage timings against OpenCV StereoSGBM's modes in the same process.

A real pair is resized to KITTI size (1242x375) and matched with D = 128 disparities. Each
stage runs once to warm up (Numba compilation, torch kernels), then `--repeat` times; the
median is reported. OpenCV runs first, each mode of gcp-stereo-eval's OPENCV_MODES (MODE_HH,
MODE_SGBM, MODE_SGBM_3WAY, at full and half size) in a block of its own; each of our times
is then given as a ratio to the fastest of them, to MODE_SGBM_3WAY at full size and to
MODE_HH. Machines are noisy: read the ratios, not the absolute seconds. The process
allocates as the node and the bag tool do (`mmap_large_arrays`); the first line names the
CPU and the load average.

`--device cpu` (the default): the default pipeline (precision 'auto') end to end as is, in
bf16 and in fp32, with `downsample` 2 (as is and in fp32) and 4, the real-time preset, and
the cost and SGM stages alone. The JSON's `modes` say how each timed pipeline and OpenCV
mode was run, for `gcp-stereo-plot rate`.
`--device cuda`: the default pipeline on the GPU (transfers included) as is, in fp32 and with
`downsample` 2, its stages as `cuda_<stage>` (each stage waits for the GPU to be timed, the
pair's own time does not); the JSON names the GPU. Without a usable GPU it says why and
exits 1.
"""
import argparse
import functools
import json
import os
from pathlib import Path
import resource
import statistics
import sys
import time
from typing import Callable

import cv2
import numpy as np
import torch

from .cli import console_main, positive_int
from .evaluate import OPENCV_MODES, opencv_sgbm
from ..evaluation.datasets import list_frames, load_frame
from ..stereo.cnn.network import resolve_precision
from ..stereo.cnn.weights import int8_entry
from ..stereo.config import StereoConfig
from ..stereo.cost import cost_volume
from ..stereo.cuda import gpu
from ..stereo.images import gray_pair
from ..stereo.memory import mmap_large_arrays
from ..stereo.pipeline import StereoPipeline
from ..stereo.sgm import aggregate

KITTI_SIZE = (1242, 375)
# Our pipelines, end to end: name -> (preset, the fields it changes).
CPU_VARIANTS: dict[str, tuple[str, dict[str, object]]] = {
    'pipeline': ('default', {}),
    'pipeline_bf16': ('default', {'precision': 'bf16'}),
    'pipeline_fp32': ('default', {'precision': 'fp32'}),
    'pipeline_downsample2': ('default', {'downsample': 2}),
    'pipeline_downsample2_fp32': ('default', {'downsample': 2, 'precision': 'fp32'}),
    'pipeline_downsample4': ('default', {'downsample': 4}),
    'pipeline_realtime': ('realtime', {}),
}
CUDA_VARIANTS: dict[str, tuple[str, dict[str, object]]] = {
    'cuda_pipeline': ('default', {'device': 'cuda'}),
    'cuda_pipeline_fp32': ('default', {'device': 'cuda', 'precision': 'fp32'}),
    'cuda_pipeline_downsample2': ('default', {'device': 'cuda', 'downsample': 2}),
}
# The peers the ratios are printed against, besides the fastest.
PEERS = ('opencv_sgbm_3way', 'opencv_sgbm_hh')


def cpu_name():
    """Return the CPU's model name (/proc/cpuinfo), its vector extensions and core count."""
    try:
        info = Path('/proc/cpuinfo').read_text()
    except OSError:
        return f'unknown CPU, {os.cpu_count()} cores'
    name = next((line.split(':', 1)[1].strip() for line in info.splitlines()
                 if line.startswith('model name')), 'unknown CPU')
    flags = set(info.split())
    extensions = [f for f in ('avx2', 'avx512f', 'avx512_vnni', 'avx512_bf16', 'amx_bf16')
                  if f in flags]
    return f'{name} ({", ".join(extensions) or "no AVX2"}), {os.cpu_count()} cores'


def gpu_name():
    """Return the first GPU's name, memory and compute capability, and torch's CUDA version."""
    p = torch.cuda.get_device_properties(0)
    return (f'{p.name}, {p.total_memory / 2 ** 30:.0f} GiB, compute capability '
            f'{p.major}.{p.minor}; torch {torch.__version__}, CUDA {torch.version.cuda}')


def median_seconds(fn: Callable[[], object], repeat: int) -> float:
    """Return the median wall time of `repeat` calls of `fn` after one to warm up."""
    fn()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def median_pipeline(pipeline: StereoPipeline, left: np.ndarray, right: np.ndarray,
                    repeat: int) -> tuple[float, dict[str, float]]:
    """
    Median end-to-end seconds of `pipeline` on the pair, and the median of each stage.

    The pair's time is measured as the node runs it; on a GPU, where nothing then waits for
    the device between stages, the stages are timed in runs of their own that wait.
    """
    runs = []
    total = median_seconds(lambda: runs.append(pipeline(left, right).seconds), repeat)
    if not pipeline.backend.host:
        runs = [pipeline(left, right, timed=True).seconds for _ in range(repeat + 1)]
    stages = runs[1:]  # not the warm-up
    return total, {k: statistics.median(s[k] for s in stages) for k in stages[0]}


def opencv_seconds(left: np.ndarray, right: np.ndarray, nd: int,
                   repeat: int) -> dict[str, float]:
    """
    Return the median seconds of each OpenCV mode, keyed 'opencv_sgbm_hh', ...

    Each mode is timed in a block of its own (its warm-up, then its `repeat` runs), with as
    many threads as OpenCV uses (`cv2.getNumThreads`).
    """
    return {name.replace('-', '_'): median_seconds(functools.partial(
        opencv_sgbm, left, right, nd, name), repeat) for name in OPENCV_MODES}


def peer_ratios(seconds: dict[str, float]) -> dict[str, dict[str, float]]:
    """
    Return each of our times in `seconds` as ratios to OpenCV's: {peer: {name: ratio}}.

    The peers are 'fastest' (the fastest OpenCV mode timed) and those of PEERS; names that
    start with 'opencv_' are OpenCV's own and have no ratio.
    """
    opencv = {k: v for k, v in seconds.items() if k.startswith('opencv_')}
    peers = {'fastest': min(opencv.values()), **{p: opencv[p] for p in PEERS}}
    return {p: {k: v / t for k, v in seconds.items() if k not in opencv}
            for p, t in peers.items()}


def volume_stage_seconds(left: np.ndarray, right: np.ndarray, nd: int,
                         repeat: int) -> dict[str, float]:
    """
    Return the median seconds of our cost and SGM stages on their own.

    Each writes into an array kept between calls, as the pipeline keeps its volumes (a fresh
    120 MB array a call would add its page faults to the stage).
    """
    census = cost_volume(left, right, nd, 'census', dtype=np.uint16)  # as the pipeline runs Census
    census_f32 = census.astype(np.float32)
    kept = {t: np.empty(census.shape, t) for t in (np.uint16, np.float32)}
    stages = {
        'census': lambda: cost_volume(left, right, nd, 'census', out=kept[np.uint16],
                                      dtype=np.uint16),
        'sad': lambda: cost_volume(left, right, nd, 'sad', out=kept[np.float32]),
        'sgm8': lambda: aggregate(census, 4, 128, 8, kept[np.uint16]),
        'sgm16': lambda: aggregate(census, 4, 128, 16, kept[np.uint16]),
        'sgm16_float32': lambda: aggregate(census_f32, 4, 128, 16, kept[np.float32]),
    }
    # The volumes are freed on return: the whole pipeline then runs with only its own arrays.
    return {name: median_seconds(fn, repeat) for name, fn in stages.items()}


@console_main('gcp-stereo-bench')
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='gcp-stereo-bench', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--dataset', default='motorcycle',
                    help="dataset of the pair (default: 'motorcycle')")
    ap.add_argument('--frame', help='frame name in that dataset (default: the first)')
    ap.add_argument('--max-disp', type=positive_int, default=128)
    ap.add_argument('--repeat', type=positive_int, default=5)
    ap.add_argument('--device', choices=('cpu', 'cuda'), default='cpu',
                    help="the pipeline's device (default cpu; cuda: 'cuda', the first GPU)")
    ap.add_argument('--json', type=Path,
                    help='write {"stages", "ratios", "modes", "device", ...} here')
    args = ap.parse_args(argv)
    if args.device == 'cuda':
        try:
            gpu.check_device('cuda')
        except ValueError as err:
            print(f'gcp-stereo-bench: {err}', file=sys.stderr)
            return 1

    mmap_large_arrays()  # the allocator as the node and the bag tool run it
    frame = load_frame(args.dataset, args.frame or list_frames(args.dataset)[0])
    left, right = (cv2.resize(g, KITTI_SIZE, interpolation=cv2.INTER_AREA)
                   for g in gray_pair(frame.left, frame.right))
    nd = args.max_disp
    load = os.getloadavg()[0]
    print(f'{frame.name} resized to {KITTI_SIZE[0]}x{KITTI_SIZE[1]}, D = {nd}, '
          f'repeat {args.repeat}; {cpu_name()}; load average {load:.2f}')
    seconds = opencv_seconds(left, right, nd, args.repeat)
    if args.device == 'cuda':
        print(f'GPU: {gpu_name()}')
        variants, device = CUDA_VARIANTS, gpu_name()
    else:
        seconds.update(volume_stage_seconds(left, right, nd, args.repeat))
        variants, device = CPU_VARIANTS, cpu_name()
    pipeline = StereoPipeline(StereoConfig(max_disp=nd))  # the default configuration
    print(f"pipeline: the defaults; precision 'auto' is "
          f"{resolve_precision('auto', args.device, int8_entry('') is not None)} here; "
          f'OpenCV on {cv2.getNumThreads()} threads')
    breakdown = {}
    for name, (preset, changes) in variants.items():
        pipe = pipeline.with_config(StereoConfig.for_cost('census', preset, max_disp=nd,
                                                          **changes))
        seconds[name], breakdown[name] = median_pipeline(pipe, left, right, args.repeat)
        if name == 'cuda_pipeline':  # every CUDA stage: upload, cnn, ..., download
            seconds.update({f'cuda_{k}': v for k, v in breakdown[name].items()})
        elif name in ('pipeline', 'pipeline_bf16', 'pipeline_fp32'):
            for stage in ('cnn', 'confidence', 'plain_sgm', 'refine'):
                seconds[stage + name[len('pipeline'):]] = breakdown[name][stage]
    ratios = peer_ratios(seconds)
    fastest = min((k for k in seconds if k.startswith('opencv_')), key=seconds.__getitem__)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    after = os.getloadavg()[0]
    print(f'{"stage":<26}{"seconds":>9}{"x fastest":>11}{"x 3WAY":>9}{"x HH":>9}')
    for name, s in seconds.items():
        cells = ''.join(f'{ratios[p][name]:{w}.2f}' if name in ratios[p] else ' ' * w
                        for p, w in zip(('fastest', *PEERS), (11, 9, 9)))
        print(f'{name:<26}{s:9.3f}{cells}')
    print(f'fastest OpenCV mode: {fastest}; peak RSS {peak:.0f} MB; load average {after:.2f} '
          'at the end')
    for name, stage_seconds in breakdown.items():
        print(f'{name} = Census+GCP+SGM end to end, preset {variants[name][0]!r}, '
              f'{variants[name][1] or "as is"}; median of its stages:',
              ', '.join(f'{k} {v:.3f} s' for k, v in stage_seconds.items()))
    if args.json:
        modes = {name: {'method': 'census+gcp', 'preset': preset, 'set': changes}
                 for name, (preset, changes) in variants.items()}
        modes.update({m.replace('-', '_'): {'method': m} for m in OPENCV_MODES})
        args.json.write_text(json.dumps({
            'stages': seconds, 'ratios': ratios, 'fastest_opencv': fastest, 'peak_rss_mb': peak,
            'device': device, 'load_average': [load, after], 'repeat': args.repeat,
            'breakdown': breakdown, 'modes': modes}, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
