"""
gcp_stereo_ros: CNN ground control points steering semi-global matching, as a ROS 2 node.

Subpackages:
- `stereo`: the method (costs, SGM, CNN, GCPs, the pipeline); numpy, Numba and torch only.
- `evaluation`: datasets with ground truth, error rates and pictures; ROS-free.
- `ros`: the node and its adapters (parameters, messages, images, sync, a private graph).
- `tools`: the console scripts (`gcp-stereo-eval`, `gcp-stereo-bag`, ...).

The public API is `StereoConfig` and `StereoPipeline`.
"""
import os

# torch and Numba each bring an OpenMP runtime; with the default (active) wait policy the
# idle threads of one spin while the other computes, slowing cost and SGM right after the
# CNN. Takes effect only if set before torch and Numba load (i.e. when this package is
# imported first); a value the user already set wins.
os.environ.setdefault('OMP_WAIT_POLICY', 'PASSIVE')

from .stereo.config import StereoConfig  # noqa: E402  (after the policy)
from .stereo.pipeline import StereoPipeline  # noqa: E402

__version__ = '0.1.0'
__all__ = ['StereoConfig', 'StereoPipeline', '__version__']
