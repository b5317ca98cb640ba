"""The package's import rule: the method is ROS-free, the ROS face never needs the tools."""
import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'gcp_stereo_ros'
ROS = {'rclpy', 'rosbags', 'rcl_interfaces', 'sensor_msgs', 'stereo_msgs', 'std_msgs',
       'diagnostic_msgs', 'builtin_interfaces', 'geometry_msgs', 'launch', 'launch_ros',
       'ament_index_python', 'message_filters', 'cv_bridge'}
# subpackage: top-level modules and gcp_stereo_ros subpackages it must not import
RULES = {
    'stereo': ROS | {'gcp_stereo_ros.ros', 'gcp_stereo_ros.tools', 'gcp_stereo_ros.evaluation'},
    'evaluation': ROS | {'gcp_stereo_ros.ros', 'gcp_stereo_ros.tools'},
    'ros': {'gcp_stereo_ros.tools', 'gcp_stereo_ros.evaluation'},
    # the network and its CPU helpers: no GPU twin, no pipeline stage
    'stereo/cnn': {'gcp_stereo_ros.stereo.cuda', 'gcp_stereo_ros.stereo.pipeline',
                   'gcp_stereo_ros.stereo.backend'},
}
# The CPU's stages never import their CUDA twins: only `backend` reaches stereo/cuda/ (lazily,
# for a GPU device).
CUDA = 'gcp_stereo_ros.stereo.cuda'


def imported(source, module):
    """Return the absolute names `source` (the text of dotted `module`) imports, lazy ones too."""
    names = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                parent = module.split('.')[:-node.level]
                base = '.'.join(parent + ([base] if base else []))
            names.update(f'{base}.{alias.name}' for alias in node.names)
            names.add(base)
    return names


def violations(names, forbidden):
    return sorted(n for n in names
                  if any(n == f or n.startswith(f + '.') for f in forbidden))


def test_the_checker_sees_every_import_form():
    source = ('import rclpy.node\nfrom ..tools import bag\n'
              'def f():\n    from ..ros.node import main\n')
    names = imported(source, 'gcp_stereo_ros.stereo.cost')
    assert violations(names, RULES['stereo']) == [
        'gcp_stereo_ros.ros.node', 'gcp_stereo_ros.ros.node.main',
        'gcp_stereo_ros.tools', 'gcp_stereo_ros.tools.bag', 'rclpy.node']


def module_name(path):
    """Return the dotted name of the module at `path`; a package's ends in __init__."""
    return '.'.join(path.relative_to(PACKAGE.parent).with_suffix('').parts)


@pytest.mark.parametrize('sub', sorted(RULES))
def test_import_rule(sub):
    files = sorted((PACKAGE / sub).rglob('*.py'))  # subpackages too
    assert len(files) >= 4, files
    for path in files:
        bad = violations(imported(path.read_text(), module_name(path)), RULES[sub])
        assert not bad, f'{path.relative_to(PACKAGE.parent)} imports {bad}'


def test_only_the_backend_reaches_the_cuda_twins():
    files = [p for p in sorted((PACKAGE / 'stereo').rglob('*.py'))
             if 'cuda' not in p.relative_to(PACKAGE).parts and p.name != 'backend.py']
    assert len(files) >= 15, files
    for path in files:
        bad = violations(imported(path.read_text(), module_name(path)), {CUDA})
        assert not bad, f'{path.relative_to(PACKAGE.parent)} imports {bad}'


def test_relative_imports_of_a_subpackage_resolve_to_their_package():
    run = module_name(PACKAGE / 'tools' / 'bag' / 'run.py')
    assert run == 'gcp_stereo_ros.tools.bag.run'
    names = imported('from ...ros import messages\nfrom .files import PROG\n', run)
    assert {'gcp_stereo_ros.ros.messages', 'gcp_stereo_ros.tools.bag.files.PROG'} <= names
    init = module_name(PACKAGE / 'tools' / 'bag' / '__init__.py')
    assert 'gcp_stereo_ros.tools.bag.make' in imported('from . import make\n', init)


MAX_LINES = 450  # past this a module holds two concerns (the developers' guide)


def test_no_module_is_over_the_line_limit():
    sizes = {str(path.relative_to(PACKAGE)): len(path.read_text().splitlines())
             for path in PACKAGE.rglob('*.py')}
    assert len(sizes) > 40 and 'tools/bag/run.py' in sizes
    over = {name: lines for name, lines in sizes.items() if lines > MAX_LINES}
    assert not over, over


# What an import inside a function may load: a dependency that not every use needs (torch
# where no GCPs are used, numba-cuda, ray, ROS where the bag tools run without it), or a
# module of the package that imports one at its top.
OPTIONAL = ROS | {'torch', 'numba.cuda', 'ray', 'rcl_interfaces'}


def module_imports():
    """Return {module: (names imported at the top, names imported inside functions)}."""
    out = {}
    for path in sorted(PACKAGE.rglob('*.py')):
        name = module_name(path)
        tree = ast.parse(path.read_text())
        lazy = set()
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for sub in ast.walk(node):
                    if isinstance(sub, (ast.Import, ast.ImportFrom)):
                        lazy |= imported(ast.unparse(sub), name)
        out[name.removesuffix('.__init__')] = (imported(path.read_text(), name) - lazy, lazy)
    return out


def package_modules(names, modules):
    """Return the modules of the package among imported `names` (a name may be a member)."""
    return {n if n in modules else n.rpartition('.')[0] for n in names
            if n in modules or n.rpartition('.')[0] in modules}


def test_no_import_circle():
    modules = module_imports()
    graph = {m: package_modules(top | lazy, modules) - {m} for m, (top, lazy) in modules.items()}
    assert 'gcp_stereo_ros.stereo.cuda.backend' in graph['gcp_stereo_ros.stereo.backend']
    state = {}

    def visit(m, trail):
        state[m] = 'open'
        for n in sorted(graph[m]):
            assert state.get(n) != 'open', f'import circle: {" -> ".join(trail + [m, n])}'
            if n not in state:
                visit(n, trail + [m])
        state[m] = 'done'

    for m in sorted(graph):
        if m not in state:
            visit(m, [])


def test_imports_inside_functions_load_only_optional_dependencies():
    modules = module_imports()
    heavy = {}

    def optional(m):
        """Tell whether importing package module `m` loads an optional dependency."""
        if m not in heavy:
            heavy[m] = False  # a circle is test_no_import_circle's to report
            top = modules[m][0]
            heavy[m] = bool(violations(top, OPTIONAL)) or any(
                optional(n) for n in package_modules(top, modules) - {m})
        return heavy[m]

    assert optional('gcp_stereo_ros.stereo.cuda.backend')
    assert optional('gcp_stereo_ros.stereo.cnn.network')
    assert not optional('gcp_stereo_ros.stereo.pipeline')  # torch only where GCPs are used
    for m, (_, lazy) in modules.items():
        plain = {n for n in lazy if not violations({n}, OPTIONAL)}
        inside = package_modules(plain, modules)
        outside = {n for n in plain if not n.startswith('gcp_stereo_ros')}
        needless = sorted(outside | {n for n in inside if not optional(n)})
        assert not needless, f'{m} imports {needless} inside a function: import it at the top'
