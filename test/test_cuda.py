"""
The CUDA pipeline: its kernels against the CPU, simulated, on a GPU if any, compiled for one.

The comparisons live in cuda_checks.py and cuda_invalidate_checks.py and run in a process of
their own: Numba's CUDA simulator is chosen by NUMBA_ENABLE_CUDASIM before numba.cuda is
first imported and stays for the life of the process, so it must not leak into (or depend
on) this one.
"""
import os
from pathlib import Path
import subprocess
import sys

import pytest

EXTRA = "device cuda is the optional extra .[cuda]: pip install 'gcp_stereo_ros[cuda]'"
pytest.importorskip('numba_cuda', reason=EXTRA)
from gcp_stereo_ros.stereo.config import StereoConfig  # noqa: E402, I100 (after the skip)
from gcp_stereo_ros.stereo.cuda import gpu  # noqa: E402
from gcp_stereo_ros.stereo.pipeline import StereoPipeline  # noqa: E402
from numba import cuda, typeof  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

HERE = Path(__file__).resolve().parent


def run_checks(simulate):
    env = {**os.environ, 'NUMBA_ENABLE_CUDASIM': '1' if simulate else '0'}
    # The sector count reads the simulator's arrays: on a GPU, the rest; whole frames: a GPU's.
    only = ['-k', 'not whole_frames' if simulate else 'not coalesced']
    for checks in ('cuda_checks.py', 'cuda_invalidate_checks.py'):  # each in its own time
        run = subprocess.run([sys.executable, '-m', 'pytest', '-q', '-p', 'no:cacheprovider',
                              str(HERE / checks), *only], env=env, cwd=HERE.parent,
                             capture_output=True, text=True, timeout=900)
        assert run.returncode == 0 and ' passed' in run.stdout and 'skipped' not in run.stdout, (
            run.stdout[-6000:] + run.stderr[-3000:])


def test_cuda_kernels_equal_the_cpu_under_the_simulator():
    run_checks(simulate=True)


def test_cuda_kernels_equal_the_cpu_on_a_gpu():
    if gpu.SIMULATED:
        pytest.skip('this process runs the CUDA simulator (NUMBA_ENABLE_CUDASIM=1)')
    try:
        gpu.check_device('cuda')
    except ValueError as err:
        pytest.skip(f'no CUDA GPU here, the kernels ran under the simulator only: {err}')
    run_checks(simulate=False)


# The kernels are compiled, not run: their outputs hold whatever the memory held, and
# the CPU stages after them may overflow on it, or meet inf - inf.
@pytest.mark.filterwarnings('ignore:overflow encountered:RuntimeWarning')
@pytest.mark.filterwarnings('ignore:invalid value encountered:RuntimeWarning')
def test_cuda_kernels_compile_for_a_gpu(data_dir, monkeypatch):
    """
    Compile each kernel as the pipeline launches it, to PTX for compute capability 7.5.

    That is numba-cuda's typing and NVVM's compilation of a real GPU run, which the
    simulator (plain Python) skips; no GPU is needed. The arguments are those of simulated
    runs of every volume type and option.
    """
    if gpu.SIMULATED:
        pytest.skip('this process runs the CUDA simulator (NUMBA_ENABLE_CUDASIM=1)')
    try:
        cuda.compile_ptx(lambda a: None, (typeof(np.zeros(1)),), cc=(7, 5))
    except Exception as err:  # any failure to find or run NVVM/NVRTC says the same
        pytest.skip(f'cannot compile for a GPU here (NVVM/NVRTC from nvidia-nvvm and '
                    f'nvidia-cuda-nvrtc): {err}')
    compiled = {}

    def compile_launch(kernel, blocks, block, shared, *args):
        types = tuple(typeof(gpu.view(a) if isinstance(a, torch.Tensor) else a) for a in args)
        key = (kernel.py_func.__name__, types)
        if key not in compiled:
            compiled[key] = cuda.compile_ptx(kernel.py_func, types, cc=(7, 5))[0]

    monkeypatch.setattr(gpu, 'SIMULATED', True)  # CPU tensors and no device checks
    monkeypatch.setattr(gpu, 'launch_blocks', compile_launch)
    rng = np.random.default_rng(0)
    left, right = rng.integers(0, 255, (2, 12, 20)).astype(np.float32)
    for config in (StereoConfig(max_disp=8, gcp_lr_check=True, subpixel=True, lr_check=True),
                   StereoConfig(max_disp=8, c_low=1.2345),  # float32 volumes
                   StereoConfig.for_cost('sad', max_disp=8, use_gcp=False)):
        StereoPipeline(config.replace(device='cuda'))(left, right)
    names = {name for name, _ in compiled}
    assert names == {'_census_transform', '_census_cost', '_sad_cost', '_select_refine',
                     '_paths', '_path_sum', '_right_winners', '_winners', '_fill_rows',
                     '_background_fits', '_links', '_sizes'}
    # every kernel once per volume type it meets (the WTA always finds the right view's
    # winners, for the confidence; the background test reads the summed costs)
    assert len(compiled) == 19 and all('.entry' in ptx for ptx in compiled.values())


def test_the_gpu_confidence_runs_float32_as_ieee_not_tf32():
    """On an H200, TF32 convolutions moved the confidence of bf16: false by up to 1.3e-3."""
    from gcp_stereo_ros.stereo.cuda.cnn import ieee_float32
    backends = (torch.backends.cudnn.conv, torch.backends.cuda.matmul)
    before = [b.fp32_precision for b in backends]
    try:
        for b in backends:  # what cuDNN does by default, and what a training script may ask
            b.fp32_precision = 'tf32'
        with ieee_float32():
            assert [b.fp32_precision for b in backends] == ['ieee', 'ieee']
        assert [b.fp32_precision for b in backends] == ['tf32', 'tf32']
    finally:
        for b, precision in zip(backends, before):
            b.fp32_precision = precision
