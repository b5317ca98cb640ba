"""The node's live parameters: declared with descriptors, validated whole, applied at once."""
from rcl_interfaces.msg import FloatingPointRange, IntegerRange
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.parameter import Parameter

from .params import (BY_NAME, check_names, coerce, config_from_params, inconsistencies,
                     PARAMS, RCLPY_PARAMS, uncrossed)


def descriptor(param):
    """Describe a `params.Param` for ROS: its description, range or choices."""
    desc = ParameterDescriptor(description=param.description)
    if param.choices:
        desc.additional_constraints = 'one of ' + ', '.join(map(str, param.choices))
    if param.range is not None:
        low, high, step = param.range
        if isinstance(param.default, int):
            desc.integer_range = [IntegerRange(from_value=low, to_value=high, step=step)]
        else:
            desc.floating_point_range = [
                FloatingPointRange(from_value=low, to_value=high, step=step)]
    return desc


def _declare(node, param):
    """
    Declare `param` with the start-up value given for it (`-p`, a params file), if any.

    The node has declared every start-up value as it came (untyped), so that none goes
    unnoticed; a whole number for a decimal parameter (`-p census.P1:=3`, `P1: 4` in a file),
    which rclpy refuses for a double, is read here and declared as the parameter's type.
    """
    value = param.default
    if node.has_parameter(param.name):
        value = node.get_parameter(param.name).value
        node.undeclare_parameter(param.name)
    node.declare_parameter(param.name, coerce(param.name, value), descriptor(param),
                           ignore_override=True)


class LiveParameters:
    """
    Declare the node's parameters and keep `values` in step with them.

    `check(config)` is given the StereoConfig that the start-up values, then the values of
    each request, ask for, and raises for one the node cannot work with (a missing weights
    file, an absent GPU), its text the reason. A start-up value for a name the node does
    not have, or that is invalid, or refused by `check`, is refused (ValueError). A request
    is validated whole, each value on its own, then by `check`, and refused with the reason
    if any value is invalid. A whole number set for a decimal parameter is taken as that
    decimal. No parameter changes another. Values that cross within a cost (P1 > P2,
    c_low > c_hi), as when `ros2 param load` sets P1 before P2, are accepted and wait
    (`check` sees them with the high value raised to the low one): `pending` says why until
    a later value uncrosses them. Once a request is taken, `on_change(names)` is called with
    the names whose values changed (none where each was set to what it was).
    """

    def __init__(self, node, check, on_change):
        self._node = node
        self._check = check
        self._on_change = on_change
        for name in node.list_parameters([], 0).names:  # declared read-only with their topic
            if name.startswith('qos_overrides.') and not node.describe_parameter(name).read_only:
                node.undeclare_parameter(name)  # (read-only: a lifecycle node configured again)
        for p in PARAMS:
            _declare(node, p)
        check_names(n for n in node.list_parameters([], 0).names  # a misspelled start-up name
                    if n not in RCLPY_PARAMS and not n.startswith('qos_overrides.'))
        self.values = {p.name: node.get_parameter(p.name).value for p in PARAMS}
        check(config_from_params(self.values))  # start-up values that cannot work stop here
        self.pending = []
        self._candidate = None
        node.add_pre_set_parameters_callback(self._as_declared)
        node.add_on_set_parameters_callback(self._validate)
        node.add_post_set_parameters_callback(self._apply)

    def close(self):
        """Stop taking part in parameter requests."""
        node = self._node
        node.remove_pre_set_parameters_callback(self._as_declared)
        node.remove_on_set_parameters_callback(self._validate)
        node.remove_post_set_parameters_callback(self._apply)

    @staticmethod
    def _as_declared(params):
        """Give a whole number for a decimal parameter its type."""
        out = []
        for p in params:
            if p.name in BY_NAME and p.type_ == Parameter.Type.INTEGER:
                try:
                    p = Parameter(p.name, value=coerce(p.name, p.value))
                except ValueError:
                    pass  # refused with its reason by _validate
            out.append(p)
        return out

    def _validate(self, params):
        changes = {p.name: p.value for p in params if p.name in BY_NAME}  # not qos_overrides.*
        self._candidate = None
        if not changes:
            return SetParametersResult(successful=True)
        values = {**self.values, **changes}
        try:
            self._check(config_from_params(uncrossed(values)))  # every value valid on its own
        except Exception as err:  # any invalid value is refused with its reason
            return SetParametersResult(successful=False, reason=str(err))
        self._candidate = values
        return SetParametersResult(successful=True)  # rclpy drops a reason given with success

    def _apply(self, params):
        if self._candidate is None:
            return
        values = self._candidate
        changed = [n for n in values if values[n] != self.values[n]]
        self.values, self.pending = values, inconsistencies(values)
        self._node.get_logger().info('parameters: ' + ', '.join(
            f'{p.name}={p.value!r}' for p in params if p.name in BY_NAME))
        self._on_change(changed)
