"""
rclpy's side of the ROS-free message builders (`messages`, `pointcloud`, `rosimage`).

Those take the message classes and a converter of uint8 numpy data as arguments; both
nodes pass these.
"""
import array

from sensor_msgs.msg import Image, PointCloud2, PointField, RegionOfInterest
from stereo_msgs.msg import DisparityImage


class RosTypes:
    """The message classes `messages` builds with: rclpy's."""

    Image = Image
    RegionOfInterest = RegionOfInterest
    DisparityImage = DisparityImage
    PointCloud2 = PointCloud2
    PointField = PointField


def ros_data(buffer):
    """Wrap uint8 numpy data as array.array('B'), the one form rclpy takes unchecked."""
    out = array.array('B')
    out.frombytes(buffer)
    return out
