"""
A launch_testing test: gcp_stereo_node behind point_cloud_node, as a stack composes them.

Both are started by `ros2 run`'s way (launch_ros finds them through the ament index); the
point cloud that point_cloud_node makes of the stereo node's disparity must be the stereo
node's own points2. launch_testing is not on PyPI (a ROS install has it): without it this
test is skipped.
"""
import time
import unittest

import pytest

launch_testing = pytest.importorskip(
    'launch_testing', reason='launch_testing is not on PyPI: it comes with a ROS 2 install '
    '(ros-jazzy-launch-testing), where colcon test runs this test')
import cv2  # noqa: E402, I100 (after the skip)
from launch import LaunchDescription  # noqa: E402
from launch_ros.actions import Node  # noqa: E402
import launch_testing.actions  # noqa: E402
import numpy as np  # noqa: E402
import rclpy  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, PointCloud2  # noqa: E402

F, BASELINE = 200.0, 0.1


@pytest.mark.launch_test
def generate_test_description():
    return LaunchDescription([
        Node(package='gcp_stereo_ros', executable='gcp_stereo_node', output='screen',
             parameters=[{'use_gcp': False, 'max_disparity': 32}]),
        Node(package='gcp_stereo_ros', executable='point_cloud_node', output='screen',
             remappings=[('left/image_rect_color', 'left/image_rect'),
                         ('points2', 'cloud/points2')]),
        launch_testing.actions.ReadyToTest(),
    ])


def pair():
    """Return a textured pair 12 px apart: x_left - x_right = 12 everywhere."""
    rng = np.random.default_rng(3)
    base = cv2.GaussianBlur((rng.random((120, 172)) * 255).astype(np.uint8), (3, 3), 0)
    return np.ascontiguousarray(base[:, :160]), np.ascontiguousarray(base[:, 12:172])


class TestStack(unittest.TestCase):

    @classmethod
    def setUpClass(cls):
        rclpy.init()
        cls.node = rclpy.create_node('stack_test')

    @classmethod
    def tearDownClass(cls):
        cls.node.destroy_node()
        rclpy.shutdown()

    def test_point_cloud_node_gives_the_stereo_nodes_points(self):
        node = self.node
        clouds = {'points2': [], 'cloud/points2': []}
        for topic, got in clouds.items():
            node.create_subscription(PointCloud2, topic, got.append, 5)
        pubs = {t: node.create_publisher(c, t, qos_profile_sensor_data) for t, c in (
            ('left/image_rect', Image), ('right/image_rect', Image),
            ('left/camera_info', CameraInfo), ('right/camera_info', CameraInfo))}
        left, right = pair()
        h, w = left.shape
        end = time.monotonic() + 120
        sec = 0
        while not all(clouds.values()):  # each second a pair, until both clouds came
            self.assertLess(time.monotonic(), end, {t: len(g) for t, g in clouds.items()})
            sec += 1
            for side, image, tx in (('left', left, 0.0), ('right', right, -F * BASELINE)):
                msg = Image(height=h, width=w, encoding='mono8', step=w, data=image.tobytes())
                info = CameraInfo(width=w, height=h, p=[F, 0.0, w / 2, tx, 0.0, F, h / 2, 0.0,
                                                        0.0, 0.0, 1.0, 0.0])
                for m in (msg, info):
                    m.header.stamp.sec = sec
                pubs[f'{side}/camera_info'].publish(info)
                pubs[f'{side}/image_rect'].publish(msg)
            stop = time.monotonic() + 1.0
            while time.monotonic() < stop:
                rclpy.spin_once(node, timeout_sec=0.05)
        stamps = {t: {m.header.stamp.sec: m for m in g} for t, g in clouds.items()}
        common = sorted(set(stamps['points2']) & set(stamps['cloud/points2']))
        end = time.monotonic() + 30
        while not common:  # the same pair from both
            self.assertLess(time.monotonic(), end)
            rclpy.spin_once(node, timeout_sec=0.1)
            stamps = {t: {m.header.stamp.sec: m for m in g} for t, g in clouds.items()}
            common = sorted(set(stamps['points2']) & set(stamps['cloud/points2']))
        own, made = (stamps[t][common[-1]] for t in ('points2', 'cloud/points2'))
        self.assertEqual((own.point_step, own.height, own.width), (made.point_step, h, w))
        xyz = [np.frombuffer(m.data, '<f4').reshape(h, w, -1)[:, :, :3] for m in (own, made)]
        np.testing.assert_array_equal(*xyz)
        z = xyz[0][:, :, 2]
        valid = np.isfinite(z)
        self.assertGreater(valid.mean(), 0.5)
        # 12 px at f 200 px and T 0.1 m: 1.667 m, within half a pixel's disparity
        self.assertLess(np.abs(np.median(z[valid]) - F * BASELINE / 12), 0.07)
