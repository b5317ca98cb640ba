"""The ROS 2 face: the node and its adapters (parameters, messages, images, sync, private graph)."""
