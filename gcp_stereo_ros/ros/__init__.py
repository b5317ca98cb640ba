"""
The ROS 2 face.

The node and its adapters (parameters, messages, images, sync, private graph).
"""
