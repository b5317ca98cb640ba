"""gcp_stereo_ros: CNN ground control points steering semi-global matching, with a ROS 2 node.

The algorithm core (images, cost, sgm, cnn, gcp, pipeline, datasets, metrics) never imports
rclpy; only `node` and the live part of `bag` do.
"""
__version__ = '0.1.0'
