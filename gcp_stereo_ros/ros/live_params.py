"""The node's live parameters: declared with descriptors, validated whole, applied at once."""
from rcl_interfaces.msg import FloatingPointRange, IntegerRange
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.parameter import Parameter

from .cnn_setup import config_warnings, load_cnn
from .params import (BY_NAME, check_names, coerce, config_from_params, inconsistencies,
                     PARAMS, RCLPY_PARAMS, uncrossed)
from .sync import image_sync
from ..stereo.pipeline import StereoPipeline


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
    Declare the node's parameters and keep `values` and `pipeline` in step with them.

    A start-up value for a name the node does not have, and start-up values the pipeline
    cannot be built with (a missing weights file, an absent GPU), are refused (ValueError).
    A request is validated whole, by building the pipeline it asks for (a missing weights
    file is refused here, with its path), and refused with the reason if any value is
    invalid. A theta above the CNN's highest confidence is warned about, at start-up and
    when set. A whole number set for a decimal parameter is taken as that decimal, a boolean
    for bf16 as 'true' or 'false' (bf16 stays a string). No
    parameter changes another. Values that cross within a cost (P1 > P2, c_low > c_hi), as when
    `ros2 param load` sets P1 before P2, are accepted and wait, with a warning: the pipeline
    keeps the last consistent values (`pending` says why) until a later value uncrosses
    them. `on_change(names)` is called with the names whose values changed.
    """

    def __init__(self, node, on_change):
        self._node = node
        self._on_change = on_change
        for name in node.list_parameters([], 0).names:  # declared read-only with their topic
            if name.startswith('qos_overrides.') and not node.describe_parameter(name).read_only:
                node.undeclare_parameter(name)  # (read-only: a lifecycle node configured again)
        for p in PARAMS:
            _declare(node, p)
        check_names(n for n in node.list_parameters([], 0).names  # a misspelled start-up name
                    if n not in RCLPY_PARAMS and not n.startswith('qos_overrides.'))
        self.values = {p.name: node.get_parameter(p.name).value for p in PARAMS}
        self.pipeline = load_cnn(StereoPipeline(config_from_params(self.values)))
        self._warn()
        self.pending = []
        self._candidate = None
        node.add_pre_set_parameters_callback(self._as_declared)
        node.add_on_set_parameters_callback(self._validate)
        node.add_post_set_parameters_callback(self._apply)

    def close(self):
        """Stop taking part in parameter requests and let the pipeline's memory go."""
        node = self._node
        node.remove_pre_set_parameters_callback(self._as_declared)
        node.remove_on_set_parameters_callback(self._validate)
        node.remove_post_set_parameters_callback(self._apply)
        self.pipeline = None

    @staticmethod
    def _as_declared(params):
        """Give a whole number for a decimal parameter, or a boolean for bf16, its type."""
        out = []
        for p in params:
            if p.name in BY_NAME and p.type_ in (Parameter.Type.INTEGER, Parameter.Type.BOOL):
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
            config = config_from_params(uncrossed(values))  # every value valid on its own
            image_sync(values)
            pipeline = load_cnn(self.pipeline.with_config(config))
        except Exception as err:  # any invalid value is refused with its reason
            return SetParametersResult(successful=False, reason=str(err))
        pending = inconsistencies(values)
        self._candidate = (values, self.pipeline if pending else pipeline, pending)
        return SetParametersResult(successful=True)  # rclpy drops a reason given with success

    def _apply(self, params):
        if self._candidate is None:
            return
        values, self.pipeline, self.pending = self._candidate
        changed = [n for n in values if values[n] != self.values[n]]
        self.values = values
        if changed:
            self._on_change(changed)
        logger = self._node.get_logger()
        logger.info('parameters: ' + ', '.join(
            f'{p.name}={p.value!r}' for p in params if p.name in BY_NAME))
        if self.pending:
            logger.warn('; '.join(self.pending) + ': waiting for that, the node keeps its last '
                        f'consistent values: {self.pipeline.config}')
        self._warn()

    def _warn(self):
        for text in config_warnings(self.pipeline):
            self._node.get_logger().warn(text)
