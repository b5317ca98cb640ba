"""The method, ROS-free: cost volumes, SGM, the Siamese CNN, GCP selection and refinement, the pipeline."""
