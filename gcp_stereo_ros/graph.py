"""Starting and stopping the node in a private ROS graph, for the demo and the load run.

No rclpy import here: these only prepare environments and processes.
"""
import os
import random
import signal
import subprocess
import sys
from pathlib import Path

SHARE = 'share/gcp_stereo_ros'


def package_file(relative):
    """A file shipped under config/ or launch/: from the source tree (editable install) or
    from <prefix>/share/gcp_stereo_ros (pip wheel, colcon install)."""
    here = Path(__file__).resolve().parent
    for root in (here.parent, *(p / SHARE for p in here.parents), Path(sys.prefix) / SHARE):
        if (root / relative).is_file():
            return root / relative
    raise FileNotFoundError(f'{relative} not found beside the package or under {SHARE}')


def private_env(domain_id=None):
    """os.environ for a graph of our own: its own DDS domain, loopback discovery only, and
    the shipped Fast DDS profile (32 MB shared memory) so large images are not dropped."""
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain_id if domain_id is not None else random.randint(1, 101))
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(package_file('config/fastdds.xml'))
    return env


def start_node(env, params=None, params_file=None):
    """The node as a child process (`python -m gcp_stereo_ros.node --ros-args ...`)."""
    cmd = [sys.executable, '-m', 'gcp_stereo_ros.node', '--ros-args']
    if params_file:
        cmd += ['--params-file', str(params_file)]
    for name, value in (params or {}).items():
        cmd += ['-p', f'{name}:={value}']
    return subprocess.Popen(cmd, env=env)


def stop(proc, timeout=10.0):
    """Ctrl-C a child, as a user would; kill it if it does not exit in time. Its exit code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode
