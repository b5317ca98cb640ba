"""
gcp-stereo-bench: stage timings against OpenCV StereoSGBM (MODE_HH) in the same process.

A real pair is resized to KITTI size (1242x375) and matched with D = 128 disparities. Each
stage runs once to warm up (Numba compilation, torch kernels), then `--repeat` times; the
median is reported, with its ratio to OpenCV's time on the same images. Machines are noisy:
read the ratios, not the absolute seconds. The process allocates as the node and the bag
tool do (`mmap_large_arrays`); the first line names the CPU.

`--device cpu` (the default): the default pipeline (precision 'auto') end to end as is, in
bf16 and in fp32, with `downsample` 2 (as is and in fp32) and 4, and the cost and SGM stages
alone.
`--device cuda`: the default pipeline on the GPU (transfers included) as is, in fp32 and with
`downsample` 2, its stages as `cuda_<stage>` (each stage waits for the GPU to be timed, the
pair's own time does not); the JSON names the GPU. Without a usable GPU it says why and
exits 1.
"""
import argparse
import json
import os
from pathlib import Path
import resource
import statistics
import sys
import time

import cv2
import numpy as np
import torch

from .cli import console_main, positive_int
from .evaluate import opencv_sgbm
from ..evaluation.datasets import list_frames, load_frame
from ..stereo import gpu
from ..stereo.cnn.network import resolve_precision
from ..stereo.cnn.weights import int8_entry
from ..stereo.config import StereoConfig
from ..stereo.cost import cost_volume
from ..stereo.images import gray_pair
from ..stereo.memory import mmap_large_arrays
from ..stereo.pipeline import StereoPipeline
from ..stereo.sgm import aggregate

KITTI_SIZE = (1242, 375)


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


def median_seconds(fn, repeat):
    fn()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def median_pipeline(pipeline, left, right, repeat):
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


def volume_stage_seconds(left, right, nd, repeat):
    """
    Return the median seconds of OpenCV and of our cost and SGM stages on their own.

    Each writes into an array kept between calls, as the pipeline keeps its volumes (a fresh
    120 MB array a call would add its page faults to the stage).
    """
    census = cost_volume(left, right, nd, 'census', dtype=np.uint16)  # as the pipeline runs Census
    census_f32 = census.astype(np.float32)
    kept = {t: np.empty(census.shape, t) for t in (np.uint16, np.float32)}
    stages = {
        'opencv_sgbm_hh': lambda: opencv_sgbm(left, right, nd),
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
                    help='write {"stages", "ratios", "peak_rss_mb", "device"} here')
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
    print(f'{frame.name} resized to {KITTI_SIZE[0]}x{KITTI_SIZE[1]}, D = {nd}, '
          f'repeat {args.repeat}; {cpu_name()}')
    variants: dict[str, dict[str, object]]
    if args.device == 'cuda':
        print(f'GPU: {gpu_name()}')
        seconds = {'opencv_sgbm_hh': median_seconds(lambda: opencv_sgbm(left, right, nd),
                                                    args.repeat)}
        variants = {'cuda_pipeline': {'device': 'cuda'},
                    'cuda_pipeline_fp32': {'device': 'cuda', 'precision': 'fp32'},
                    'cuda_pipeline_downsample2': {'device': 'cuda', 'downsample': 2}}
        device = gpu_name()
    else:
        seconds = volume_stage_seconds(left, right, nd, args.repeat)
        variants = {'pipeline': {}, 'pipeline_bf16': {'precision': 'bf16'},
                    'pipeline_fp32': {'precision': 'fp32'},
                    'pipeline_downsample2': {'downsample': 2},
                    'pipeline_downsample2_fp32': {'downsample': 2, 'precision': 'fp32'},
                    'pipeline_downsample4': {'downsample': 4}}
        device = cpu_name()
    pipeline = StereoPipeline(StereoConfig(max_disp=nd))  # the default configuration
    print(f"pipeline: the defaults; precision 'auto' is "
          f"{resolve_precision('auto', args.device, int8_entry('') is not None)} here")
    breakdown = {}
    for name, changes in variants.items():
        pipe = pipeline.with_config(pipeline.config.replace(**changes))
        seconds[name], breakdown[name] = median_pipeline(pipe, left, right, args.repeat)
        if name == 'cuda_pipeline':  # every CUDA stage: upload, cnn, ..., download
            seconds.update({f'cuda_{k}': v for k, v in breakdown[name].items()})
        elif name in ('pipeline', 'pipeline_bf16', 'pipeline_fp32'):
            for stage in ('cnn', 'confidence', 'plain_sgm', 'refine'):
                seconds[stage + name[len('pipeline'):]] = breakdown[name][stage]
    peer = seconds['opencv_sgbm_hh']
    ratios = {name: s / peer for name, s in seconds.items() if name != 'opencv_sgbm_hh'}
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f'{"stage":<24}{"seconds":>9}{"ours/opencv":>13}')
    for name, s in seconds.items():
        print(f'{name:<24}{s:9.3f}{ratios.get(name, 1.0):13.2f}')
    print(f'peak RSS {peak:.0f} MB')
    for name, stage_seconds in breakdown.items():
        print(f'{name} = default Census+GCP+SGM end to end, {variants[name] or "as is"}; '
              'median of its stages:',
              ', '.join(f'{k} {v:.3f} s' for k, v in stage_seconds.items()))
    if args.json:
        args.json.write_text(json.dumps({'stages': seconds, 'ratios': ratios, 'peak_rss_mb': peak,
                                         'device': device, 'repeat': args.repeat,
                                         'breakdown': breakdown}, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
