"""
The method, ROS-free.

Cost volumes, SGM, the Siamese CNN, GCP selection and refinement, the pipeline.
"""
