"""
Sphinx directive ``gcp-parameters``: the node's parameter table, made from its descriptors.

Each row is what the node declares (``params.PARAMS``, each with the ParameterDescriptor of
``live_params.descriptor``, what ``ros2 param describe`` prints): the name, the ROS type
rclpy gives the default, the default, the range or the choices, and the description. So
the manual's table cannot drift from the code.
"""
from docutils import nodes
from docutils.parsers.rst import Directive

HEADER = ('parameter', 'type', 'default', 'range', 'description')
WIDTHS = (22, 8, 10, 18, 42)


def ros_type(value):
    """Return the ROS parameter type name of `value`, as `ros2 param describe` says it."""
    from rcl_interfaces.msg import ParameterType
    from rclpy.parameter import Parameter
    names = {ParameterType.PARAMETER_BOOL: 'boolean', ParameterType.PARAMETER_INTEGER:
             'integer', ParameterType.PARAMETER_DOUBLE: 'double',
             ParameterType.PARAMETER_STRING: 'string'}
    return names[Parameter.Type.from_parameter_value(value).value]


def default_text(value):
    """Return a default as a params file writes it: true / false, quoted strings."""
    if isinstance(value, bool):
        return str(value).lower()
    return repr(value)


def range_text(descriptor):
    """Return a descriptor's range (`low .. high`, with its step if any) or its choices."""
    ranges = [*descriptor.integer_range, *descriptor.floating_point_range]
    texts = [f'{r.from_value!r} .. {r.to_value!r}' + (f' step {r.step!r}' if r.step else '')
             for r in ranges]
    if descriptor.additional_constraints:
        texts.append(descriptor.additional_constraints)
    return '; '.join(texts)


def rows():
    """Return (name, type, default, range, description) of every parameter the node declares."""
    from gcp_stereo_ros.ros.live_params import descriptor
    from gcp_stereo_ros.ros.params import coerce, PARAMS
    table = []
    for param in PARAMS:
        value = coerce(param.name, param.default)  # what the node declares
        desc = descriptor(param)
        table.append((param.name, ros_type(value), default_text(value), range_text(desc),
                      desc.description))
    return table


def _entry(text, literal=False):
    entry = nodes.entry()
    paragraph = nodes.paragraph()
    if text:
        paragraph += nodes.literal(text, text) if literal else nodes.Text(text)
    entry += paragraph
    return entry


class ParameterTable(Directive):
    """The table of the node's parameters (no arguments, no content)."""

    has_content = False

    def run(self):
        try:
            table_rows = rows()
        except ImportError as err:  # a warning, which `make docs` (-W) turns into an error
            return [self.state.document.reporter.warning(
                f'gcp-parameters: the package does not import ({err}): no parameter table',
                line=self.lineno)]
        table = nodes.table(classes=['gcp-parameters'])
        group = nodes.tgroup(cols=len(HEADER))
        table += group
        group.extend(nodes.colspec(colwidth=width) for width in WIDTHS)
        head = nodes.thead()
        head += nodes.row('', *(_entry(text) for text in HEADER))
        body = nodes.tbody()
        for name, kind, default, limits, description in table_rows:
            body += nodes.row('', _entry(name, True), _entry(kind), _entry(default, True),
                              _entry(limits), _entry(description))
        group += head
        group += body
        return [table]


def setup(app):
    """Register the directive with Sphinx."""
    app.add_directive('gcp-parameters', ParameterTable)
    return {'parallel_read_safe': True, 'parallel_write_safe': True, 'version': '1'}
