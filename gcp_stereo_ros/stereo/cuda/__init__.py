"""
The pipeline on a GPU: `CudaBackend` and the CUDA twin of each CPU stage beside it.

numba-cuda kernels over torch tensors in GPU memory; `gpu` holds the device helpers and
`lanes` the warp-lane kernels SGM shares. Imported only for ``device: cuda``.
"""
