"""`python -m gcp_stereo_ros.tools.bag`: the gcp-stereo-bag console script."""
import sys

from . import main

sys.exit(main())
