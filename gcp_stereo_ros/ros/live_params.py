"""The node's live parameters: declared with descriptors, validated whole, applied at once."""
from rcl_interfaces.msg import FloatingPointRange, IntegerRange
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.parameter import Parameter

from .params import BY_NAME, config_from_params, cost_defaults, make_sync, PARAMS, SYNC_PARAMS
from ..stereo.cost import COSTS
from ..stereo.pipeline import StereoPipeline


def descriptor(param):
    """Describe a `params.Param` for ROS: its description and range."""
    desc = ParameterDescriptor(description=param.description, dynamic_typing=param.dynamic)
    if param.range is not None:
        low, high, step = param.range
        if isinstance(param.default, int):
            desc.integer_range = [IntegerRange(from_value=low, to_value=high, step=step)]
        else:
            desc.floating_point_range = [
                FloatingPointRange(from_value=low, to_value=high, step=step)]
    return desc


def config_of(values):
    """Build the StereoConfig of ROS-named values (node-only parameters left out)."""
    return config_from_params({n: v for n, v in values.items() if BY_NAME[n].field})


class LiveParameters:
    """
    Declare the node's parameters and keep `values` and `pipeline` in step with them.

    A request is validated whole, by building the pipeline it asks for (a missing weights
    file is refused here, with its path), and applied only if every value is valid.
    Switching `cost` brings that cost's theta, P1, P2, c_hi and c_low unless set in the
    same request. `on_sync_change(values)` is called when a sync parameter changes.
    """

    def __init__(self, node, on_sync_change):
        self._node = node
        self._on_sync_change = on_sync_change
        # Cost-dependent parameters default to the chosen cost's values; overrides win.
        cost = node.declare_parameter(
            'cost', BY_NAME['cost'].default, descriptor(BY_NAME['cost'])).value
        defaults = cost_defaults(cost) if cost in COSTS else {}
        for p in PARAMS:
            if p.name != 'cost':
                node.declare_parameter(p.name, defaults.get(p.name, p.default), descriptor(p))
        self.values = {p.name: node.get_parameter(p.name).value for p in PARAMS}
        self.pipeline = StereoPipeline(config_of(self.values))
        self._candidate = None
        node.add_pre_set_parameters_callback(self._complete_cost_switch)
        node.add_on_set_parameters_callback(self._validate)
        node.add_post_set_parameters_callback(self._apply)

    def _complete_cost_switch(self, params):
        names = {p.name for p in params}
        for p in params:
            if p.name == 'cost' and p.value != self.values['cost'] and p.value in COSTS:
                params += [Parameter(n, value=v) for n, v in cost_defaults(p.value).items()
                           if n not in names]
        return params

    def _validate(self, params):
        changes = {p.name: p.value for p in params if p.name in BY_NAME}  # not qos_overrides.*
        self._candidate = None
        if not changes:
            return SetParametersResult(successful=True)
        values = {**self.values, **changes}
        try:
            config = config_of(values)
            make_sync(values)
            pipeline = self.pipeline.with_config(config)
            if config.use_gcp:
                pipeline.net
        except Exception as err:  # any invalid value is refused with its reason
            return SetParametersResult(successful=False, reason=str(err))
        self._candidate = (values, pipeline)
        return SetParametersResult(successful=True)

    def _apply(self, params):
        if self._candidate is None:
            return
        values, self.pipeline = self._candidate
        sync_changed = any(values[n] != self.values[n] for n in SYNC_PARAMS)
        self.values = values
        if sync_changed:
            self._on_sync_change(values)
        self._node.get_logger().info('parameters: ' + ', '.join(
            f'{p.name}={p.value!r}' for p in params if p.name in BY_NAME))
