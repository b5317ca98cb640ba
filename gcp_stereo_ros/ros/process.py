"""
A node as a process: its command line, its signals, its exit status.

Shared by gcp_stereo_node, gcp_stereo_lifecycle_node and point_cloud_node.
"""
import gc
import os
import signal
import sys

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.utilities import remove_ros_args

from .params import check_params_files
from ..stereo.memory import mmap_large_arrays


def _cannot_start(err, prog):
    """Print why the node cannot start, in one line; return the exit status."""
    print(f'{prog}: error: cannot start: ' + (' '.join(str(err).split()) or repr(err)),
          file=sys.stderr)
    return 2


def _stop_once(signum, frame):
    """
    Stop on the first SIGINT or SIGTERM (KeyboardInterrupt) and ignore every later one.

    Installed before rclpy.init, whose own handlers (which wake the executor) call it after
    theirs. `ros2 launch` forwards the terminal's Ctrl-C, so the node gets two at once; a
    second KeyboardInterrupt while stopping would abort the exit (with the worker thread
    alive, the interpreter then dies in `terminate`).
    """
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    raise KeyboardInterrupt


def run_node(node_class, doc, prog, args=None):
    """
    Run `node_class` until Ctrl-C, SIGTERM or shutdown; return the exit status.

    `args` is the command line (sys.argv if None): `-h`/`--help` prints `doc`; anything but
    ROS arguments, or settings the node cannot start with, end it with one line naming
    `prog` and status 2. A node whose `stopped` is false at the end (a worker thread still
    running) ends the process at once.
    """
    argv = sys.argv if args is None else args
    try:
        check_params_files(argv)  # rcl would say it with a traceback
        extra = remove_ros_args(argv)[1:]
    except Exception as err:  # rcl's own argument errors
        return _cannot_start(err, prog)
    if extra and extra[0] in ('-h', '--help'):
        print(doc.strip())
        return 0
    if extra:  # ROS arguments go after --ros-args; anything else is a mistake
        print(f'{prog}: error: unrecognized arguments: {" ".join(extra)} '
              '(parameters go after --ros-args, e.g. --ros-args -p NAME:=VALUE)',
              file=sys.stderr)
        return 2
    node = None
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _stop_once)
    try:
        try:
            mmap_large_arrays()
            rclpy.init(args=argv)
            node = node_class()
        except Exception as err:  # settings that cannot work: one line, no traceback
            return _cannot_start(err, prog)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # Ctrl-C or shutdown, while starting or spinning
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):  # stopping for another reason: the same
            signal.signal(sig, signal.SIG_IGN)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if node is not None and not node.stopped:  # the interpreter's exit would abort on it
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    gc.freeze()  # else the interpreter's exit collects every object (doc/failures.md)
    return 0
