"""The private ROS graph of the demo and load tools, and the Fast DDS segment size."""
import threading
import time

from gcp_stereo_ros.ros.graph import package_file, private_env, shm_segment_bytes, Spinner
from ros_helpers import wait_for


def test_private_graph_keeps_the_users_domain(monkeypatch):
    monkeypatch.setenv('ROS_DOMAIN_ID', '42')
    assert private_env()['ROS_DOMAIN_ID'] == '42'
    assert private_env(7)['ROS_DOMAIN_ID'] == '7'  # an explicit domain wins (the tests')
    monkeypatch.delenv('ROS_DOMAIN_ID')
    assert 1 <= int(private_env()['ROS_DOMAIN_ID']) <= 101  # none set: a random one


def test_private_graph_drops_the_deprecated_localhost_variable(monkeypatch):
    # Jazzy's rcl warns on stderr about ROS_LOCALHOST_ONLY; loopback comes from the range
    monkeypatch.setenv('ROS_LOCALHOST_ONLY', '1')
    env = private_env()
    assert 'ROS_LOCALHOST_ONLY' not in env
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'


def test_shm_segment_size_is_read_from_the_profile(tmp_path):
    profile = {'FASTRTPS_DEFAULT_PROFILES_FILE': str(package_file('config/fastdds.xml'))}
    assert shm_segment_bytes(profile) == 32 << 20
    assert shm_segment_bytes({}) == 512 << 10  # Fast DDS's default
    broken = tmp_path / 'broken.xml'
    broken.write_text('<profiles><transport_descriptors>')
    assert shm_segment_bytes({'FASTRTPS_DEFAULT_PROFILES_FILE': str(broken)}) == 512 << 10


def test_spinner_stops_after_the_callback_in_progress(ros):
    """Stopped mid-callback, it returns once the callback is done, and nothing is raised."""
    from rclpy.node import Node
    from std_msgs.msg import String
    node, peer = Node('spinner_test'), Node('spinner_test_peer')
    started, done, errors = threading.Event(), [], []

    def slow(msg):
        started.set()
        time.sleep(0.3)
        done.append(msg.data)
    sub = node.create_subscription(String, 'spinner_test', slow, 10)
    pub = peer.create_publisher(String, 'spinner_test', 10)
    hook, threading.excepthook = threading.excepthook, errors.append
    spinner = Spinner(node)
    try:
        wait_for(lambda: pub.get_subscription_count() and sub.get_publisher_count(), 'matched')
        pub.publish(String(data='in progress'))
        assert started.wait(10)
        spinner.stop()
        assert done == ['in progress']  # finished before stop returned
    finally:
        threading.excepthook = hook
        node.destroy_node()
        peer.destroy_node()
    assert not errors, errors[0].exc_value
