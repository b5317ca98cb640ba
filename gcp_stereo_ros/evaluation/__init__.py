"""Evaluation data, ROS-free: datasets with ground truth, error rates, pictures for people."""
