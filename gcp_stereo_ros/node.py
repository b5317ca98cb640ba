"""`python -m gcp_stereo_ros.node`: the node's entry point (see `gcp_stereo_ros.ros.node`)."""
import sys

from .ros.node import main

if __name__ == '__main__':
    sys.exit(main())
