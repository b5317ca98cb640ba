"""
Launch gcp_stereo_node with the paper's parameters and the large-image Fast DDS profile.

    ros2 launch gcp_stereo_ros gcp_stereo.launch.py namespace:=stereo

Topics are relative to the namespace: left/image_rect, right/image_rect, left/camera_info,
right/camera_info in; disparity, gcp_mask, confidence out.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    share = get_package_share_directory('gcp_stereo_ros')
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value=''),
        DeclareLaunchArgument(
            'params_file', default_value=os.path.join(share, 'config', 'gcp_stereo.yaml')),
        SetEnvironmentVariable(
            'FASTRTPS_DEFAULT_PROFILES_FILE', os.path.join(share, 'config', 'fastdds.xml')),
        Node(
            package='gcp_stereo_ros',
            executable='gcp_stereo_node',
            name='gcp_stereo_node',
            namespace=LaunchConfiguration('namespace'),
            parameters=[LaunchConfiguration('params_file')],
            output='screen',
        ),
    ])
