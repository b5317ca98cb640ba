"""
The exchange between the lanes of a group that shares one SGM path or one WTA pixel.

A group is `lanes(D)` consecutive threads of a warp (8, 16 or 32, aligned within the warp),
lane l holding d = l, l + lanes, l + 2 lanes, ... of the D disparities. The kernels of
`cuda.sgm` call the two functions here for whatever crosses lanes: `exchange` (each lane's
cyclic neighbours' values and the group's minimum: one SGM step) and `lanes_argmin` (the
group's first minimum: the WTA).

Each has two bodies, chosen when this module is imported by what numba.cuda is in the process
(`gpu.SIMULATED` says the same, but a test that compiles for a GPU without one sets it):
warp shuffles within the group's mask on a GPU (no block barrier: groups step on
independently), and shared memory with one block barrier a call under Numba's CUDA
simulator, which has no shuffles. The simulator's body needs `exchange_bytes` of dynamic
shared memory per block (0 on a GPU), and the block's threads to call it in step until they
return (its barrier waits for the block's live threads: a thread that has returned drops
out). Minima are exact in any order, so both bodies give the same bits. Blocks are
(lanes, THREADS // lanes) threads: a group of 32 is then a whole warp.
"""
import numba
from numba import cuda, float32, njit

from . import gpu

WARP = 32  # the most lanes a group has
THREADS = gpu.THREADS  # per block: THREADS // lanes groups


def lanes(nd: int) -> int:
    """Return the threads a path (or a WTA pixel) of D = `nd` disparities gets: 8, 16 or 32."""
    return min(WARP, max(8, 1 << (nd - 1).bit_length()))


def per_lane(nd: int) -> int:
    """Return the disparities each lane holds for D = `nd`: D / lanes(D), rounded up."""
    return -(-nd // lanes(nd))


if numba.config.ENABLE_CUDASIM:  # type: ignore[attr-defined]
    def exchange_bytes(k: int) -> int:
        """Return the dynamic shared memory (bytes) a block of `exchange` over k values needs."""
        return 4 * 2 * THREADS * (k + 1)  # two steps (parity) of each thread's k values and low

    @cuda.jit(device=True)
    def exchange(values: gpu.DeviceArray, low: float, lane: int, nl: int, step: int,
                 above: gpu.DeviceArray, below: gpu.DeviceArray) -> float:
        """
        Set above[i], below[i] to values[i] of lane (lane -+ 1) mod nl; return the lanes' min low.

        `values`, `above`, `below`: a local array each of k float32; `step` counts the calls
        (its parity picks the half of shared memory: one barrier a call).
        """
        k = values.shape[0]
        shared = cuda.shared.array(0, float32)
        me = cuda.threadIdx.y * nl + lane  # this thread in the block
        half = (step % 2) * THREADS * (k + 1)
        for i in range(k):
            shared[half + me * (k + 1) + i] = values[i]
        shared[half + me * (k + 1) + k] = low
        cuda.syncthreads()
        first = me - lane
        up = half + (first + (lane + nl - 1) % nl) * (k + 1)
        down = half + (first + (lane + 1) % nl) * (k + 1)
        for i in range(k):
            above[i] = shared[up + i]
            below[i] = shared[down + i]
        for j in range(nl):
            low = min(low, shared[half + (first + j) * (k + 1) + k])
        return low

    @cuda.jit(device=True)
    def lanes_argmin(low: float, at: int, lane: int, nl: int, step: int) -> tuple[float, int]:
        """
        Return (v, a): the least (low, at) of the group's lanes, the least `at` among ties.

        Needs exchange_bytes(1) of dynamic shared memory; `step` as for `exchange`.
        """
        shared = cuda.shared.array(0, float32)
        me = cuda.threadIdx.y * nl + lane
        half = (step % 2) * THREADS * 2
        shared[half + 2 * me] = low
        shared[half + 2 * me + 1] = at  # an index below 2^24: exact
        cuda.syncthreads()
        for j in range(me - lane, me - lane + nl):
            v, a = shared[half + 2 * j], int(shared[half + 2 * j + 1])
            if v < low or (v == low and a < at):
                low, at = v, a
        return low, at
else:
    def exchange_bytes(k: int) -> int:
        """Return the dynamic shared memory a block of `exchange` needs: none (shuffles)."""
        return 0

    # njit, inlined into the kernels: it types and compiles for a GPU without one (a
    # cuda.jit device function asks for the current device when a kernel calling it compiles)
    @njit(inline='always')
    def _mask(lane: int, nl: int) -> tuple[int, int]:
        """Return (the group's first lane in its warp, the group's lanes as a warp mask)."""
        if nl == WARP:  # the whole warp: a constant mask makes the convergence check cheaper
            return 0, 0xFFFFFFFF
        first = cuda.laneid - lane
        return first, ((1 << nl) - 1) << first

    @njit(inline='always')
    def exchange(values: gpu.DeviceArray, low: float, lane: int, nl: int, step: int,
                 above: gpu.DeviceArray, below: gpu.DeviceArray) -> float:
        """
        Set above[i], below[i] to values[i] of lane (lane -+ 1) mod nl; return the lanes' min low.

        `values`, `above`, `below`: a local array each of k float32 (k and nl constants of
        the caller, so the loops unroll into registers); `step` unused here.
        """
        first, mask = _mask(lane, nl)
        up = first + (lane + nl - 1) % nl
        down = first + (lane + 1) % nl
        for i in range(values.shape[0]):
            above[i] = cuda.shfl_sync(mask, values[i], up)
            below[i] = cuda.shfl_sync(mask, values[i], down)
        span = nl // 2
        while span > 0:  # a butterfly: every lane ends with the minimum
            low = min(low, cuda.shfl_xor_sync(mask, low, span))
            span //= 2
        return low

    @njit(inline='always')
    def lanes_argmin(low: float, at: int, lane: int, nl: int, step: int) -> tuple[float, int]:
        """Return (v, a): the least (low, at) of the group's lanes, the least `at` among ties."""
        mask = _mask(lane, nl)[1]
        span = nl // 2
        while span > 0:
            v = cuda.shfl_xor_sync(mask, low, span)
            a = cuda.shfl_xor_sync(mask, at, span)
            if v < low or (v == low and a < at):
                low, at = v, a
            span //= 2
        return low, at
