"""The console scripts, each also `python -m gcp_stereo_ros.tools.<name>`."""
