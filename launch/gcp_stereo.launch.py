"""
Launch gcp_stereo_node with its default parameters and the large-image Fast DDS profile.

    ros2 launch gcp_stereo_ros gcp_stereo.launch.py namespace:=stereo
    ros2 launch gcp_stereo_ros gcp_stereo.launch.py lifecycle:=true  # managed, unconfigured
    ros2 launch gcp_stereo_ros gcp_stereo.launch.py --show-args

Topics are relative to the namespace: left/image_rect, right/image_rect, left/camera_info,
right/camera_info in; disparity, gcp_mask, confidence, depth, points2, disparity_color
out. The shipped
Fast DDS profile is used unless FASTRTPS_DEFAULT_PROFILES_FILE is set already.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
from launch.substitutions import EnvironmentVariable, LaunchConfiguration, PythonExpression
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

PROFILES = 'FASTRTPS_DEFAULT_PROFILES_FILE'


def generate_launch_description():
    share = get_package_share_directory('gcp_stereo_ros')
    return LaunchDescription([
        DeclareLaunchArgument(
            'namespace', default_value='',
            description='namespace of the node and its topics, e.g. stereo'),
        DeclareLaunchArgument(
            'params_file', default_value=os.path.join(share, 'config', 'gcp_stereo.yaml'),
            description='parameters file of the node (config/gcp_stereo_paper.yaml holds the '
                        "paper's values)"),
        DeclareLaunchArgument(
            'use_sim_time', default_value='false', choices=['true', 'false'],
            description='use the /clock topic as time (e.g. ros2 bag play --clock; '
                        'gcp-stereo-bag play publishes no /clock)'),
        DeclareLaunchArgument(
            'lifecycle', default_value='false', choices=['true', 'false'],
            description='run gcp_stereo_lifecycle_node, a managed node that starts '
                        'unconfigured (ros2 lifecycle set, or a lifecycle manager)'),
        # A profile the user set already (their own DDS set-up) is kept.
        SetEnvironmentVariable(PROFILES, EnvironmentVariable(
            PROFILES, default_value=os.path.join(share, 'config', 'fastdds.xml'))),
        Node(
            package='gcp_stereo_ros',
            executable=PythonExpression([
                "'gcp_stereo_lifecycle_node' if '", LaunchConfiguration('lifecycle'),
                "' == 'true' else 'gcp_stereo_node'"]),
            name='gcp_stereo_node',
            namespace=LaunchConfiguration('namespace'),
            parameters=[LaunchConfiguration('params_file'), {
                'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'),
                                               value_type=bool)}],
            output='screen',
        ),
    ])
