"""The private ROS graph of the demo and load tools, and the Fast DDS segment size."""
from gcp_stereo_ros.ros.graph import package_file, private_env, shm_segment_bytes


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
