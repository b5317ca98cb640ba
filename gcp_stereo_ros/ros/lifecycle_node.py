"""
gcp_stereo_lifecycle_node: gcp_stereo_node as a managed (lifecycle) node, as nav2 runs its nodes.

The same node, parameters, topics and outputs as gcp_stereo_node, brought up in steps by
`ros2 lifecycle set /gcp_stereo_node <transition>` or a lifecycle manager:
  configure   declares and checks the parameters and loads the CNN weights (a value that
              cannot work fails the transition, saying why, and the node stays unconfigured)
  activate    starts the worker, subscribes the inputs and publishes the outputs
  deactivate  stops the frame in progress, unsubscribes and unpublishes
  cleanup     lets the pipeline's memory and the CNN go
  shutdown    from any state, all of the above that applies, within 2 s
Start: `ros2 run gcp_stereo_ros gcp_stereo_lifecycle_node` (unconfigured), or the launch file
with `lifecycle:=true`.
"""
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn

from .node import GcpStereoNode
from .params import NODE_NAME
from .process import run_node


class GcpStereoLifecycleNode(GcpStereoNode, LifecycleNode):

    def __init__(self, **kwargs):
        LifecycleNode.__init__(self, NODE_NAME,
                               automatically_declare_parameters_from_overrides=True, **kwargs)

    def on_configure(self, state):
        try:
            self.configure()
        except Exception as err:  # a value that cannot work: say why, stay unconfigured
            self.get_logger().error(f'cannot configure: {" ".join(str(err).split())}')
            return TransitionCallbackReturn.FAILURE
        self.get_logger().info(f'configured: {self.pipeline.config}')
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state):
        self.activate()
        return super().on_activate(state)

    def on_deactivate(self, state):
        self.deactivate()
        return super().on_deactivate(state)

    def on_cleanup(self, state):
        self.cleanup()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state):
        if self.active:
            self.on_deactivate(state)
        if self.params is not None:
            self.on_cleanup(state)
        return TransitionCallbackReturn.SUCCESS

    def destroy_node(self):
        """
        Shut down, destroy the node, and its state machine with it.

        rclpy's LifecycleNode (Jazzy 7.1) leaves its state machine, which holds the rcl node,
        to the garbage collector, which would then take rcl's /rosout publisher of the
        node's name from a later node of that name (doc/notes/implementation_history.md).
        """
        self.on_shutdown(None)
        LifecycleNode.destroy_node(self)
        self._state_machine.destroy_when_not_in_use()


def main(args: list[str] | None = None) -> int:
    return run_node(GcpStereoLifecycleNode, __doc__, 'gcp_stereo_lifecycle_node', args)
