"""
Starting and stopping the node in a private ROS graph, for the demo and the load run.

Also the Fast DDS shared-memory segment size, which bounds the messages the graph carries.
rclpy is imported only inside `Spinner` and `peer_graph`, after the environment it reads
is set.
"""
from contextlib import contextmanager
import os
from pathlib import Path
import random
import signal
import subprocess
import sys
import sysconfig
import threading
from xml.etree import ElementTree

SHARE = 'share/gcp_stereo_ros'
FASTDDS_SHM_DEFAULT = 512 * 1024  # Fast DDS's shared-memory segment without a profile


def package_file(relative):
    """
    Return the path of a file shipped under config/ or launch/.

    It is found in the source tree (editable install) or in <prefix>/share/gcp_stereo_ros
    (pip wheel, colcon install).
    """
    here = Path(__file__).resolve().parents[1]  # the gcp_stereo_ros package
    for root in (here.parent, *(p / SHARE for p in here.parents), Path(sys.prefix) / SHARE):
        if (root / relative).is_file():
            return root / relative
    raise FileNotFoundError(f'{relative} not found beside the package or under {SHARE}')


def executable(name):
    """
    Return the path of this package's executable `name`, as `ros2 run` finds it.

    That is <prefix>/lib/gcp_stereo_ros/<name> under the package's prefix in the ament
    index (a colcon install, or any prefix on AMENT_PREFIX_PATH), else the scripts folder
    of this interpreter (where pip puts console scripts).
    """
    from ament_index_python.packages import get_package_prefix, PackageNotFoundError
    try:
        path = Path(get_package_prefix('gcp_stereo_ros')) / 'lib' / 'gcp_stereo_ros' / name
        if path.is_file():
            return path
    except (PackageNotFoundError, OSError):  # OSError: no AMENT_PREFIX_PATH at all
        pass
    return Path(sysconfig.get_path('scripts')) / name


def private_env(domain_id=None):
    """
    Return os.environ for a graph of our own.

    The graph gets loopback discovery only, the shipped Fast DDS profile (32 MiB shared
    memory) so large images are not dropped, and DDS domain `domain_id`, else the user's
    ROS_DOMAIN_ID, else a random one. ROS_LOCALHOST_ONLY, which Jazzy replaces by
    ROS_AUTOMATIC_DISCOVERY_RANGE and warns about on stderr, is left out.
    """
    env = dict(os.environ)
    env.pop('ROS_LOCALHOST_ONLY', None)
    if domain_id is not None or not env.get('ROS_DOMAIN_ID'):
        env['ROS_DOMAIN_ID'] = str(domain_id if domain_id is not None
                                   else random.randint(1, 101))
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(package_file('config/fastdds.xml'))
    return env


def join_private_graph(domain_id=None):
    """Make this process's environment `private_env(domain_id)`, which its children inherit."""
    env = private_env(domain_id)
    for name in set(os.environ) - set(env):  # what private_env leaves out
        del os.environ[name]
    os.environ.update(env)


def shm_segment_bytes(env=None):
    """
    Return the Fast DDS shared-memory segment size, in bytes, of processes started in `env`.

    That is the largest SHM `segment_size` in the FASTRTPS_DEFAULT_PROFILES_FILE profile, or
    Fast DDS's default without one. A message larger than the publisher's segment is lost.
    """
    path = (os.environ if env is None else env).get('FASTRTPS_DEFAULT_PROFILES_FILE')
    try:
        root = ElementTree.parse(path).getroot() if path else None
    except (OSError, ElementTree.ParseError):
        root = None
    sizes = []
    for e in root.iter() if root is not None else ():
        fields = {c.tag.rsplit('}', 1)[-1]: (c.text or '').strip() for c in e}
        if fields.get('type') == 'SHM' and fields.get('segment_size', '').isdigit():
            sizes.append(int(fields['segment_size']))
    return max(sizes, default=FASTDDS_SHM_DEFAULT)


def start_node(env, params=None, params_file=None):
    """Start the node as a child process (`python -m gcp_stereo_ros.node --ros-args ...`)."""
    cmd = [sys.executable, '-m', 'gcp_stereo_ros.node', '--ros-args']
    if params_file:
        cmd += ['--params-file', str(params_file)]
    for name, value in (params or {}).items():
        cmd += ['-p', f'{name}:={value}']
    return subprocess.Popen(cmd, env=env)


class Spinner:
    """
    Nodes spun in a thread of their own, one callback at a time, as `rclpy.spin` spins one.

    `stop` ends the loop after the callback in progress and joins the thread, so that the
    nodes can be destroyed, then shuts the executor down. Jazzy's `Executor.shutdown` waits
    for nothing: it destroys the executor's guard condition at once, and a
    MultiThreadedExecutor's callbacks still queued in its pool then fail on it ("cannot use
    Destroyable because destruction was requested", which rclpy prints at exit as an
    exception never retrieved).
    """

    def __init__(self, *nodes, context=None):
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.task import Future
        self.executor = SingleThreadedExecutor(context=context)
        for node in nodes:
            self.executor.add_node(node)
        self._stopped = Future()
        self._thread = threading.Thread(target=self.executor.spin_until_future_complete,
                                        args=(self._stopped,), daemon=True)
        self._thread.start()

    def stop(self, timeout=10.0):
        """Stop spinning, wait up to `timeout` s for the thread, then shut the executor down."""
        self._stopped.set_result(True)
        self._thread.join(timeout)
        if self._thread.is_alive():
            raise RuntimeError(f'a callback still runs after {timeout} s')
        self.executor.shutdown()


@contextmanager
def peer_graph(peer_name, params=None, params_file=None):
    """
    Yield (peer, node) for the node run in a private graph.

    `node` is the node started as a child process in a private graph (this process's
    environment becomes `private_env()`, so children such as `gcp-stereo-bag play` join it
    too) and `peer` an rclpy node `peer_name` of ours spinning in a thread. On exit the peer
    is destroyed and the node stopped with Ctrl-C (`node.returncode` holds its exit code).
    """
    join_private_graph()
    import rclpy  # after the environment is set: rclpy reads it at init
    from rclpy.node import Node

    node = start_node(os.environ, params, params_file)
    rclpy.init(args=[])  # our argv is not for rcl
    peer = Node(peer_name)
    spinner = Spinner(peer)
    try:
        yield peer, node
    finally:
        try:
            spinner.stop()
        finally:  # the node stops even if a callback of the peer hangs
            peer.destroy_node()
            rclpy.try_shutdown()
            stop(node)


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
