"""The managed node: each lifecycle transition does what it says, with real rclpy."""
import gc
import time
import weakref

import cv2
from gcp_stereo_ros.ros.graph import Spinner
from gcp_stereo_ros.ros.lifecycle_node import GcpStereoLifecycleNode
import pytest
from rcl_interfaces.msg import Log
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from ros_helpers import image_msg, wait_for
from sensor_msgs.msg import Image
from skimage import data
from stereo_msgs.msg import DisparityImage

SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE


@pytest.fixture
def graph(ros):
    """Yield start(**overrides): a lifecycle node (unconfigured) and a peer, spun in a thread."""
    made = []

    def start(**overrides):
        node = GcpStereoLifecycleNode(
            parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()])
        peer = Node('lifecycle_peer')
        made.append((Spinner(node, peer), node, peer))
        return node, peer
    yield start
    for spinner, node, peer in made:
        spinner.stop()
        node.destroy_node()
        peer.destroy_node()


def entities(node):
    """Return the node's publishers, subscriptions, timers and guard conditions, by kind."""
    return {kind: set(getattr(node, kind))
            for kind in ('publishers', 'subscriptions', 'timers', 'guards')}


def test_transitions(graph):
    left, right, _ = data.stereo_motorcycle()
    pair = [cv2.resize(im, (247, 167), interpolation=cv2.INTER_AREA) for im in (left, right)]
    node, peer = graph(max_disparity=32)
    assert node.params is None and node.pipeline is None  # no CNN yet
    assert not node.has_parameter('census.theta')
    assert node.trigger_configure() == SUCCESS
    assert node.pipeline.net is not None and node.has_parameter('census.theta')
    assert not peer.get_publishers_info_by_topic('/disparity')  # nothing published yet
    configured = entities(node)
    disparity = []
    peer.create_subscription(DisparityImage, 'disparity', disparity.append, 10)
    pubs = {side: peer.create_publisher(Image, f'{side}/image_rect', qos_profile_sensor_data)
            for side in ('left', 'right')}
    for cycle in range(2):  # activate and deactivate twice: the second time as the first
        assert node.trigger_activate() == SUCCESS
        wait_for(lambda: all(p.get_subscription_count() for p in pubs.values())
                 and all(s.get_publisher_count() for s in node.input.subs.values()), 'matched')
        stamp = (cycle + 1) * 1_000_000_000
        for side, array in zip(pubs, pair):
            pubs[side].publish(image_msg(array, 'rgb8', stamp))
        wait_for(lambda: disparity and disparity[-1].header.stamp.sec == cycle + 1, 'disparity')
        assert node.trigger_deactivate() == SUCCESS
        assert node.stopped  # the worker thread has ended
        assert entities(node) == configured  # all that activate made is destroyed
        wait_for(lambda: not any(p.get_subscription_count() for p in pubs.values())
                 and not peer.get_publishers_info_by_topic('/disparity'), 'unsubscribed')
    # set while inactive: taken, and subscribed by the next activate only
    assert node.set_parameters([Parameter('image_transport', value='compressed')])[0].successful
    assert entities(node) == configured
    net = weakref.ref(node.pipeline.net)
    assert node.trigger_cleanup() == SUCCESS and node.params is None and node.pipeline is None
    assert net() is None  # the CNN is gone, not waiting for a garbage collection
    assert node.trigger_configure() == SUCCESS  # and again, with the declared values
    assert node.get_parameter('max_disparity').value == 32
    assert node.trigger_activate() == SUCCESS
    assert node.input.topics() == {side: f'/{side}/image_rect/compressed'
                                   for side in ('left', 'right')}
    start = time.monotonic()
    assert node.trigger_shutdown() == SUCCESS
    assert time.monotonic() - start < 2.0 and node.stopped
    assert node.params is None and node.pipeline is None and not node.active


def test_configure_fails_with_the_reason(graph):
    node, _ = graph(weights='/no/such/weights.pt')
    assert node.trigger_configure() == FAILURE  # still unconfigured
    assert node.params is None and node.pipeline is None
    assert node.set_parameters([Parameter('weights', value='')])[0].successful
    assert node.trigger_configure() == SUCCESS  # once fixed, it configures
    assert node.pipeline.config.weights == ''


def test_a_destroyed_node_is_gone_and_leaves_the_logs_of_its_name(ros):
    """
    Destroy a lifecycle node, start another of its name: the new one's logs reach /rosout.

    rcl keeps one /rosout publisher per logger name. rclpy's LifecycleNode left its state
    machine, and with it the rcl node, to the garbage collector, which then took that
    publisher from the new node: in the test suite, the log lines of test_node's nodes
    stopped at a random point after this module.
    """
    old = GcpStereoLifecycleNode(parameter_overrides=[Parameter('max_disparity', value=32)])
    assert old.trigger_configure() == SUCCESS and old.trigger_activate() == SUCCESS
    old.destroy_node()
    new, peer = Node('gcp_stereo_node'), Node('lifecycle_peer')
    logs = []
    peer.create_subscription(Log, '/rosout', logs.append, QoSProfile(
        depth=1000, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    spinner = Spinner(peer)
    try:
        del old
        gc.collect()  # what the garbage collector does at some point
        new.get_logger().info('still heard')
        wait_for(lambda: any(m.msg == 'still heard' and m.name == 'gcp_stereo_node'
                             for m in logs), 'the new node on /rosout', 10)
    finally:
        spinner.stop()
        new.destroy_node()
        peer.destroy_node()
