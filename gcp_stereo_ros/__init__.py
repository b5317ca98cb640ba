"""gcp_stereo_ros: CNN ground control points steering semi-global matching, with a ROS 2 node.

The algorithm core (images, cost, sgm, cnn, gcp, pipeline, datasets, metrics) never imports
rclpy; only `node` and the live part of `bag` do.
"""
import os

__version__ = '0.1.0'

# torch and Numba each bring an OpenMP runtime; with the default (active) wait policy the
# idle threads of one spin while the other computes, which made cost and SGM 2-3x slower
# right after the CNN on 2 cores. Passive waiting costs nothing here. Takes effect only if
# set before torch and Numba load (i.e. when this package is imported first); a value the
# user already set wins.
os.environ.setdefault('OMP_WAIT_POLICY', 'PASSIVE')
