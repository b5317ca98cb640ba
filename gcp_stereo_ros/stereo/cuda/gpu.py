"""
Device arrays and kernel launches of the CUDA pipeline (StereoConfig.device 'cuda[:N]').

Every array on the GPU is a torch tensor (torch's caching allocator serves the CNN and the
volumes alike); the numba-cuda kernels get zero-copy views of them (`view`) and run on the
default stream, which torch uses too, so the stages follow each other without a
synchronization. Under Numba's CUDA simulator (NUMBA_ENABLE_CUDASIM=1 in the environment
before numba.cuda is first imported; the tests use it) the same kernels run in Python
threads on the CPU, on CPU tensors: slow, for small crops only.
"""
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numba
import numpy as np
import torch

try:
    from numba import cuda
except ImportError:  # numba-cuda is an optional extra
    cuda = None

MISSING = ("device 'cuda' needs numba-cuda, an optional extra of this package: "
           "pip install 'gcp_stereo_ros[cuda]' (and a CUDA build of torch), or use device 'cpu'")

SIMULATED = bool(numba.config.ENABLE_CUDASIM)  # type: ignore[attr-defined]
THREADS = 128  # threads per block of every launch
# numpy type -> torch type of the volumes (cost.volume_type)
VOLUME_TYPES: dict[np.dtype, Any] = {np.dtype(np.float32): torch.float32,
                                     np.dtype(np.uint16): torch.uint16}
# What a kernel takes for a tensor (`view`): a numba-cuda device array, a numpy array when
# simulated; also the kernels' own local and shared arrays.
DeviceArray = Any


def index(device: str) -> int:
    """Return N of 'cuda:N' (0 for 'cuda')."""
    return int(device.partition(':')[2] or 0)


def check_device(device: str) -> None:
    """Raise ValueError unless numba-cuda and torch can both use the GPU `device` names."""
    n = index(device)
    if cuda is None:
        raise ValueError(f'device {device!r}: {MISSING}')
    if SIMULATED:
        if n != 0:
            raise ValueError(f"device {device!r}: the CUDA simulator has one device, 'cuda:0'")
        return
    if not cuda.is_available():
        reason = ' '.join(str(cuda.cuda_error() or 'no device').split())
        raise ValueError(f'device {device!r}: numba-cuda finds no usable CUDA GPU ({reason}); '
                         "use device 'cpu'")
    if not torch.cuda.is_available():
        raise ValueError(f'device {device!r}: torch {torch.__version__} cannot use the GPU '
                         '(a CPU build, or a CUDA build too new for the driver); '
                         "install a CUDA build of torch or use device 'cpu'")
    if n >= torch.cuda.device_count():
        raise ValueError(f'device {device!r}: there are {torch.cuda.device_count()} CUDA GPUs')


def torch_device(device: str) -> torch.device:
    """Return the torch device of the CUDA pipeline on `device` (the CPU when simulated)."""
    return torch.device('cpu') if SIMULATED else torch.device('cuda', index(device))


@contextmanager
def current(device: str) -> Iterator[None]:
    """Make `device` the current GPU of numba-cuda and torch for the duration."""
    if SIMULATED:
        yield
        return
    with cuda.gpus[index(device)], torch.cuda.device(index(device)):
        yield


def numpy_type(volume: torch.Tensor) -> np.dtype:
    """Return the numpy dtype of a volume tensor."""
    return next(k for k, v in VOLUME_TYPES.items() if v == volume.dtype)


def view(tensor: torch.Tensor) -> DeviceArray:
    """Return what a kernel takes for `tensor`: a view, no copy."""
    # No synchronization: torch and the kernels share the default stream, which orders them.
    return tensor.numpy() if SIMULATED else cuda.as_cuda_array(tensor, sync=False)


def launch(kernel: Any, n: int, *args: Any) -> None:
    """Run `kernel` on at least `n` threads (a 1-D grid); tensors among `args` as views."""
    launch_blocks(kernel, -(-n // THREADS), THREADS, 0, *args)


def launch_blocks(kernel: Any, blocks: int, block: int | tuple[int, ...], shared: int,
                  *args: Any) -> None:
    """
    Run `kernel` on `blocks` blocks of shape `block` with `shared` bytes of dynamic memory.

    Tensors among `args` are passed as views.
    """
    args = [view(a) if isinstance(a, torch.Tensor) else a  # type: ignore[assignment]
            for a in args]
    kernel[max(1, blocks), block, 0, shared](*args)


def synchronize() -> None:
    """Wait for the GPU's work so far (for stage timings)."""
    if not SIMULATED:
        cuda.synchronize()
