"""point_cloud_node with real rclpy: stereo_image_proc's interface, the stereo node's geometry."""
import array

import cv2
from gcp_stereo_ros.ros import messages
from gcp_stereo_ros.ros.camera import stereo_model
from gcp_stereo_ros.ros.graph import Spinner
from gcp_stereo_ros.ros.params import config_from_params
from gcp_stereo_ros.ros.point_cloud_node import PointCloudNode
from gcp_stereo_ros.ros.rclpy_messages import ros_data, RosTypes
from gcp_stereo_ros.stereo.pipeline import StereoPipeline
import numpy as np
import pytest
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from ros_helpers import BASELINE, CX_OFFSET, F, image_msg, stamped, wait_for
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from skimage import data
from stereo_msgs.msg import DisparityImage

FRAME = 'left_camera'
FIRST, SECOND = 1_000_000_000, 2_000_000_000  # the stamps (ns) of the two tests' messages


def infos(shape, p_zero=False):
    h, w = shape[:2]
    out = {}
    for side, cx, tx in (('left', w / 2, 0.0), ('right', w / 2 - CX_OFFSET, -F * BASELINE)):
        p = [0.0] * 12 if p_zero else [F, 0.0, cx, tx, 0.0, F, h / 2, 0.0, 0.0, 0.0, 1.0, 0.0]
        out[side] = CameraInfo(width=w, height=h, p=p)
    return out


@pytest.fixture(scope='module')
def frame():
    """Motorcycle at a third: the disparity the stereo node publishes for it, and its model."""
    left, right, _ = data.stereo_motorcycle()
    left, right = (cv2.resize(im, (247, 167), interpolation=cv2.INTER_AREA)
                   for im in (left, right))
    config = config_from_params({'use_gcp': False, 'max_disparity': 32})
    result = StereoPipeline(config)(left, right)
    info = infos(left.shape)
    model = stereo_model(info['left'], info['right'], left.shape, config.max_disp)
    disparity = messages.disparity_message(RosTypes, stamped(Image(), FIRST, FRAME).header,
                                           result.disparity, config, model, ros_data)
    return left, result, model, info, disparity


@pytest.fixture
def graph():
    rclpy.init()
    nodes = []

    def start(cli_args=(), **params):
        node = PointCloudNode(
            cli_args=list(cli_args),
            parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        nodes.append(node)
        return node
    peer = Node('point_cloud_peer')
    spinner = Spinner(peer)
    yield start, spinner.executor, peer
    spinner.stop()
    for node in [*nodes, peer]:
        node.destroy_node()
    rclpy.shutdown()


def send_all(peer, nodes, msgs):
    """Publish {topic: message} with the sensor-data QoS once every end has matched."""
    pubs = {t: peer.create_publisher(type(m), t, qos_profile_sensor_data) for t, m in msgs.items()}
    subs = [s for node in nodes for s in node.subscriptions]
    wait_for(lambda: all(p.get_subscription_count() == len(nodes) for p in pubs.values())
             and all(s.get_publisher_count() for s in subs), 'matched')
    for topic, msg in msgs.items():
        pubs[topic].publish(msg)


def listen(peer, node, topic, cls):
    got = []
    peer.create_subscription(cls, topic, got.append, 10)
    wait_for(lambda: node._pubs[topic.rsplit('/', 1)[-1]].get_subscription_count(), topic)
    assert node._pubs[topic.rsplit('/', 1)[-1]].topic_name == '/' + topic
    return got


def cloud(msg):
    fields = msg.point_step // 4
    return np.frombuffer(msg.data, '<f4').reshape(msg.height, msg.width, fields)


def test_points_and_depth_equal_the_stereo_nodes(graph, frame):
    """From the stereo node's DisparityImage: its points2 and depth, bit for bit."""
    left, result, model, info, disparity = frame
    start, executor, peer = graph
    node = start(avoid_point_cloud_padding=True)
    executor.add_node(node)
    points, depth = listen(peer, node, 'points2', PointCloud2), listen(peer, node, 'depth', Image)
    send_all(peer, [node], {'left/image_rect_color': image_msg(left, 'bgr8', FIRST, FRAME),
                            'disparity': disparity,
                            'left/camera_info': stamped(info['left'], FIRST, FRAME),
                            'right/camera_info': stamped(info['right'], FIRST, FRAME)})
    wait_for(lambda: points and depth, 'points2 and depth')
    want = messages.output_messages(RosTypes, disparity.header, {'points2', 'depth'}, result,
                                    config_from_params({'max_disparity': 32}), model, left,
                                    padded=False, data=ros_data)
    assert points[0].point_step == 16 and points[0].header.frame_id == 'left_camera'
    np.testing.assert_array_equal(cloud(points[0]), cloud(want['points2']))
    got_depth = np.frombuffer(depth[0].data, '<f4').reshape(depth[0].height, depth[0].width)
    np.testing.assert_array_equal(got_depth, np.frombuffer(want['depth'].data, '<f4')
                                  .reshape(got_depth.shape))
    valid = np.isfinite(got_depth)
    assert 0.5 < valid.mean() < 1.0  # the invalid (min_disparity - 1) pixels are NaN
    assert np.isnan(cloud(points[0])[~valid][:, :3]).all()


def test_uncalibrated_float64_input_gives_nan_points(graph, frame):
    """What stereo_image_proc's own test sends: P all zero, f = t = 0, float64, no encoding."""
    left, result, *_ = frame
    start, executor, peer = graph
    rgb = start(use_color=True)
    xyz = start(['--ros-args', '-r', '__node:=point_cloud_node_xyz', '-r', 'points2:=xyz/points2'],
                use_color=False)  # as in stereo_image_proc's test
    for node in (rgb, xyz):
        executor.add_node(node)
    clouds = [listen(peer, n, t, PointCloud2) for n, t in ((rgb, 'points2'), (xyz, 'xyz/points2'))]
    h, w = result.disparity.shape
    disparity = stamped(DisparityImage(), SECOND, FRAME)
    disparity.image.height, disparity.image.width, disparity.image.step = h, w, 4 * w
    disparity.image.data = array.array('B', np.nan_to_num(result.disparity).astype(float)
                                       .tobytes())
    info = infos(left.shape, p_zero=True)
    send_all(peer, [rgb, xyz], {
        'left/image_rect_color': image_msg(left, 'bgr8', SECOND, FRAME),
        'left/camera_info': stamped(info['left'], SECOND, FRAME),
        'right/camera_info': stamped(info['right'], SECOND, FRAME), 'disparity': disparity})
    wait_for(lambda: all(clouds), 'both clouds')
    assert [c[0].point_step for c in clouds] == [32, 16]
    assert all(np.isnan(cloud(c[0])[:, :, :3]).all() for c in clouds)
