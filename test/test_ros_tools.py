"""
The node as the ROS 2 tools drive it, without them installed.

`ros2 param` calls the parameter services with rclpy's AsyncParameterClient (dump: ListParameters,
then GetParameters of the sorted names; load: SetParameters, one value at a time, in file
order; set: one SetParameters); `--params-file` and `-r` are parsed by rcl; `ros2 run` and
`ros2 launch` find the package through the ament index of a colcon install. The code quoted
is ros2cli's and launch_ros' jazzy branches.
"""
import importlib.util
import os
from pathlib import Path
import re
import shutil
import subprocess
import sys
import time
from types import ModuleType, SimpleNamespace

from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.ros.graph import Spinner
from gcp_stereo_ros.ros.node import GcpStereoNode
from gcp_stereo_ros.ros.params import config_from_params
from gcp_stereo_ros.ros.rosimage import image_to_array
from gcp_stereo_ros.stereo.pipeline import StereoPipeline
from gcp_stereo_ros.tools import bag
from gcp_stereo_ros.tools.bag import files as bag_files
import numpy as np
import pytest
from rcl_interfaces.msg import ParameterType
import rclpy
from rclpy.context import Context
from rclpy.parameter import get_parameter_value, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
import yaml

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO / 'config' / 'gcp_stereo_paper.yaml'
QUICK = ['-p', 'use_gcp:=false', '-p', 'max_disparity:=16']  # no CNN: quick to start


class Graph:
    """The node started with command-line `args` in a context of its own, and a client."""

    def __init__(self, args):
        self.context = Context()
        rclpy.init(args=['gcp_stereo_node', '--ros-args', *args], context=self.context)
        self.node = GcpStereoNode(context=self.context)
        self.client_node = rclpy.create_node('ros2cli_stand_in', context=self.context,
                                             use_global_arguments=False)  # not renamed
        self.spinner = Spinner(self.node, self.client_node, context=self.context)
        self.name = self.node.get_fully_qualified_name()
        self.client = AsyncParameterClient(self.client_node, self.name)
        assert self.client.wait_for_services(timeout_sec=10)

    def call(self, future):
        end = time.monotonic() + 30
        while not future.done():
            assert time.monotonic() < end, 'no answer from the parameter services'
            time.sleep(0.01)
        return future.result()

    def get(self, *names):
        values = self.call(self.client.get_parameters(list(names))).values
        return [parameter_value_to_python(v) for v in values]

    def types(self, *names):
        return [v.type for v in self.call(self.client.get_parameters(list(names))).values]

    def dump(self, path):
        """Write what `ros2 param dump` prints (ros2param/verb/dump.py)."""
        names = sorted(self.call(self.client.list_parameters()).result.names)
        params = {}
        for name, value in zip(names, self.get(*names)):
            *groups, last = name.split('.')  # DumpVerb.insert_dict
            node = params
            for group in groups:
                node = node.setdefault(group, {})
            node[last] = value
        path.write_text(yaml.dump({self.name: {'ros__parameters': params}},
                                  default_flow_style=False))
        return path

    def load(self, path):
        """Do what `ros2 param load` does (ros2param.api.load_parameter_file); the results."""
        return self.call(self.client.load_parameter_file(str(path), use_wildcard=True)).results

    def set_text(self, name, text):
        """Do what `ros2 param set NODE NAME TEXT` does: the value typed as the CLI types it."""
        msg = rclpy.parameter.Parameter(name).to_parameter_msg()
        msg.value = get_parameter_value(string_value=text)
        result, = self.call(self.client.set_parameters([msg])).results
        return result

    def close(self):
        self.spinner.stop()
        self.node.destroy_node()
        self.client_node.destroy_node()
        rclpy.shutdown(context=self.context)


@pytest.fixture
def graph():
    graphs = []

    def start(*args):
        graphs.append(Graph(args))
        return graphs[-1]
    yield start
    for g in graphs:
        g.close()


@pytest.mark.parametrize('remap', [['-r', '__ns:=/stereo'], ['-r', '__node:=left_stereo'],
                                   ['-r', '__ns:=/car/front', '-r', '__node:=stereo']])
def test_shipped_params_file_applies_under_any_name(graph, remap):
    """`namespace:=stereo` in the launch file, `-r __ns:=`, `-r __node:=` (rcl parses the file)."""
    g = graph('--params-file', str(PAPER), *remap, *QUICK)
    assert g.get('census.theta', 'census.P1', 'census.c_low', 'gcp_lr_check', 'sad.P2') == [
        0.6, 4.0, 1.3, False, 14.0]  # the defaults differ: census.P1 12.0, sad.P2 0.5, ...


def test_dump_then_load_restores_exactly_what_was_dumped(graph, tmp_path):
    g = graph('-r', '__ns:=/stereo', *QUICK)
    for name, text in [('sad.P2', '30.0'), ('sad.P1', '2.0'), ('census.P2', '64.0'),
                       ('census.c_low', '2.0'), ('census.c_hi', '5.0'), ('sad.theta', '0.7'),
                       ('sad.window', '7'), ('cost', 'sad'), ('paths', '8'),
                       ('approximate_sync', 'true')]:
        assert g.set_text(name, text).successful, name
        assert not g.node.params.pending, name
    dumped = g.dump(tmp_path / 'dump.yaml')
    doc = yaml.safe_load(dumped.read_text())
    assert list(doc) == ['/stereo/gcp_stereo_node']
    before = doc['/stereo/gcp_stereo_node']['ros__parameters']
    for name, text in [('cost', 'census'), ('sad.P1', '0.02'), ('sad.P2', '0.5'),
                       ('census.c_hi', '200.0'), ('census.c_low', '10.0'), ('census.P2', '128.0'),
                       ('paths', '16'), ('approximate_sync', 'false')]:
        assert g.set_text(name, text).successful, name
    # Alphabetical: census.c_hi 5 before census.c_low 2 (c_low 10 > 5 meanwhile), cost
    # before sad.*, sad.P1 2 before sad.P2 30 (P2 0.5 < 2 meanwhile): values that cross wait.
    results = g.load(dumped)
    names = list(rclpy.parameter.parameter_dict_from_yaml_file(str(dumped), True))
    failed = {n for n, r in zip(names, results, strict=True) if not r.successful}
    # Only what every rclpy node refuses to change: read-only QoS and type-description flags.
    assert failed and all(n.startswith('qos_overrides.') or n == 'start_type_description_service'
                          for n in failed), failed
    after = yaml.safe_load(g.dump(tmp_path / 'again.yaml').read_text())
    assert after['/stereo/gcp_stereo_node']['ros__parameters'] == before
    config = g.node.pipeline.config
    assert not g.node.params.pending
    assert (config.cost, config.p1, config.p2, config.theta, config.window, config.paths) == (
        'sad', 2.0, 30.0, 0.7, 7, 8)


def test_bag_run_takes_a_dump_file(graph, tmp_path):
    g = graph('-r', '__ns:=/stereo', *QUICK, '-p', 'cost:=sad', '-p', 'sad.P2:=20.0')
    dumped = g.dump(tmp_path / 'dump.yaml')
    bag_in, bag_out = tmp_path / 'in', tmp_path / 'out'
    assert bag.main(['make', '--dataset', 'motorcycle', '--out', str(bag_in)]) == 0
    proc = subprocess.run([sys.executable, '-m', 'gcp_stereo_ros.tools.bag', 'run', '--in',
                           str(bag_in), '--out', str(bag_out), '--params', str(dumped)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    frame = load_frame('motorcycle', 'motorcycle')
    pipeline = StereoPipeline(config_from_params(g.node.params.values))
    want = pipeline(frame.left, frame.right).disparity
    with bag_files.open_bag(bag_out) as reader:
        disp, = (bag_files.deserialize(raw, c, t, bag_out) for c, t, raw in reader.messages()
                 if c.topic == '/disparity')
    low = np.float32(frame.doffs_px)  # published: d - (cx_left - cx_right), calibrated bag
    assert disp.min_disparity == low and disp.f > 0
    np.testing.assert_array_equal(image_to_array(disp.image),
                                  np.where(np.isnan(want), low - 1, want + low))
    assert g.node.pipeline.config.p2 == 20.0


def test_whole_numbers_for_decimal_parameters(graph, tmp_path):
    params = tmp_path / 'ints.yaml'
    params.write_text('/**:\n  ros__parameters:\n    census:\n      P2: 100\n      c_hi: 300\n')
    g = graph('--params-file', str(params), '-p', 'census.P1:=3', *QUICK)
    assert g.get('census.P1', 'census.P2', 'census.c_hi') == [3.0, 100.0, 300.0]
    assert g.types('census.P1', 'census.P2') == [ParameterType.PARAMETER_DOUBLE] * 2
    assert g.set_text('census.P2', '300').successful  # `ros2 param set` sends an integer
    assert g.get('census.P2') == [300.0]
    assert g.types('census.P2') == [ParameterType.PARAMETER_DOUBLE]
    params.write_text('/**:\n  ros__parameters:\n    census:\n      P1: 4\n')
    assert all(r.successful for r in g.load(params))  # `ros2 param load` too
    assert g.node.pipeline.config.p1 == 4.0
    refused = g.set_text('census.P2', 'many')
    assert not refused.successful and 'type' in refused.reason


def test_descriptors_admit_only_values_the_node_takes(graph):
    """`ros2 param describe` shows ranges and choices; every value they admit is taken."""
    g = graph(*QUICK)
    names = g.call(g.client.list_parameters()).result.names
    descriptors = {d.name: d for d in g.call(g.client.describe_parameters(names)).descriptors}
    paths = descriptors['paths']
    assert not paths.integer_range and paths.additional_constraints == 'one of 4, 8, 16'
    assert descriptors['cost'].additional_constraints == 'one of census, sad'
    tried = 0
    for name, d in descriptors.items():
        if d.integer_range:
            r = d.integer_range[0]
            for value in sorted({r.from_value, r.from_value + r.step, r.to_value}):
                assert g.set_text(name, str(value)).successful, (name, value)
                tried += 1
        for choice in re.findall(r'\w+', d.additional_constraints)[2:]:
            assert g.set_text(name, choice).successful, (name, choice)
            tried += 1
    assert tried >= 20
    refused = g.set_text('paths', '12')
    assert not refused.successful and 'paths must be one of 4, 8, 16' in refused.reason
    assert not g.set_text('census.window', '13').successful  # beyond census' range
    assert g.set_text('sad.window', '13').successful


# ---- packaging: colcon build, colcon test, ros2 run, ros2 launch ----------------------------
def test_colcon_test_finds_the_pytest_runner():
    """
    Read the package as colcon does (colcon-python-setup-py: run_setup, stop_after='config').

    colcon-core runs pytest when a 'test' dependency names it; setuptools no longer keeps
    `tests_require`, so only `extras_require['test']` counts.
    """
    code = ('from distutils.core import run_setup; '
            "d = run_setup('setup.py', script_args=('--dry-run',), stop_after='config'); "
            "print(repr({k: getattr(d, k, None) for k in ('tests_require', 'extras_require')}))")
    proc = subprocess.run([sys.executable, '-c', code], cwd=REPO, capture_output=True,
                          text=True, check=True)
    data = eval(proc.stdout.strip().splitlines()[-1])  # noqa: S307 (our own repr of literals)
    test_deps = list(data['tests_require'] or []) + [
        d for key in ('test', 'tests', 'testing') for d in (data['extras_require'] or {}).get(
            key, [])]
    assert any(re.split(r' |<|=|>|!', d)[0] == 'pytest' for d in test_deps), data


@pytest.fixture(scope='module')
def colcon_install(tmp_path_factory):
    """Install the package as `colcon build` does (its exact setup.py command) into a prefix."""
    tmp = tmp_path_factory.mktemp('colcon')
    src, build, prefix = tmp / 'src', tmp / 'build', tmp / 'install'
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(
        '.venv', '.git', 'build', 'install', 'log', 'out', '*.egg-info', '__pycache__'))
    build.mkdir()
    subprocess.run([sys.executable, 'setup.py', 'egg_info', '--egg-base', str(build), 'build',
                    '--build-base', str(build / 'build'), 'install', '--prefix', str(prefix),
                    '--record', str(build / 'install.log'), '--install-scripts',
                    '$base/lib/gcp_stereo_ros', '--single-version-externally-managed',
                    'install_data'], cwd=src, check=True, capture_output=True)
    site = next(prefix.glob('lib/python3*/site-packages'))
    return SimpleNamespace(prefix=prefix, site=site)


def test_ros2_run_finds_every_command_after_a_colcon_install(colcon_install, monkeypatch):
    from ament_index_python.packages import get_package_prefix, get_package_share_directory
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(colcon_install.prefix))
    prefix = Path(get_package_prefix('gcp_stereo_ros'))
    share = Path(get_package_share_directory('gcp_stereo_ros'))
    assert prefix == colcon_install.prefix
    for relative in ('package.xml', 'config/gcp_stereo.yaml', 'config/gcp_stereo_paper.yaml',
                     'config/fastdds.xml', 'launch/gcp_stereo.launch.py'):
        assert (share / relative).is_file(), relative
    # ros2pkg.api.get_executable_paths: executable files under <prefix>/lib/<package>
    lib = prefix / 'lib' / 'gcp_stereo_ros'
    found = {p.name for p in lib.iterdir() if os.access(p, os.X_OK)}
    scripts = set(re.findall(r"'([\w-]+) = gcp_stereo_ros", (REPO / 'setup.py').read_text()))
    assert found == scripts and {'gcp_stereo_node', 'gcp-stereo-bag'} <= scripts
    assert not (prefix / 'bin').exists()  # so the README says `ros2 run gcp_stereo_ros ...`
    readme = (REPO / 'README.md').read_text()
    assert all(f'ros2 run gcp_stereo_ros {s}' in readme
               for s in ('gcp-stereo-bag', 'gcp_stereo_node'))
    env = {**os.environ, 'PYTHONPATH': str(colcon_install.site)}  # what setup.bash adds
    proc = subprocess.run([str(lib / 'gcp-stereo-bag'), '--help'], env=env, cwd='/',
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and 'usage: gcp-stereo-bag' in proc.stdout, proc.stderr


class _Recorded:
    """Stands in for a launch class: keeps its arguments to compare."""

    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs

    def __eq__(self, other):
        return (type(self), self.args, self.kwargs) == (type(other), other.args, other.kwargs)

    def __repr__(self):
        return f'{type(self).__name__}{self.args}{self.kwargs}'


def test_launch_file(colcon_install, monkeypatch):
    """
    Evaluate the installed launch file with launch's classes stood in for (not on PyPI).

    launch's EnvironmentVariable(name, default_value=...) gives the variable's value when it
    is set and the default otherwise, so a user's own Fast DDS profile is kept.
    """
    classes = {'launch': ['LaunchDescription'],
               'launch.actions': ['DeclareLaunchArgument', 'SetEnvironmentVariable'],
               'launch.substitutions': ['EnvironmentVariable', 'LaunchConfiguration',
                                        'PythonExpression'],
               'launch_ros.actions': ['Node'],
               'launch_ros.parameter_descriptions': ['ParameterValue']}
    fake = {}
    for module, names in classes.items():
        mod = ModuleType(module)
        for name in names:
            fake[name] = type(name, (_Recorded,), {})
            setattr(mod, name, fake[name])
        monkeypatch.setitem(sys.modules, module, mod)
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(colcon_install.prefix))
    share = colcon_install.prefix / 'share' / 'gcp_stereo_ros'
    spec = importlib.util.spec_from_file_location('launch_file',
                                                  share / 'launch' / 'gcp_stereo.launch.py')
    launch_file = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(launch_file)
    actions, = launch_file.generate_launch_description().args
    arguments = {a.args[0]: a.kwargs for a in actions
                 if isinstance(a, fake['DeclareLaunchArgument'])}
    assert set(arguments) == {'namespace', 'params_file', 'use_sim_time', 'lifecycle'}
    assert all(len(a['description']) > 20 for a in arguments.values()), arguments
    assert arguments['use_sim_time']['default_value'] == 'false'
    assert arguments['lifecycle']['default_value'] == 'false'
    assert Path(arguments['params_file']['default_value']).is_file()
    env, = (a for a in actions if isinstance(a, fake['SetEnvironmentVariable']))
    profiles = 'FASTRTPS_DEFAULT_PROFILES_FILE'
    assert env == fake['SetEnvironmentVariable'](profiles, fake['EnvironmentVariable'](
        profiles, default_value=str(share / 'config' / 'fastdds.xml')))
    node, = (a for a in actions if isinstance(a, fake['Node']))
    (expression,) = node.kwargs['executable'].args  # lifecycle:=true: the managed node
    text = ''.join(x if isinstance(x, str) else f'{x.args[0]!r}' for x in expression)
    assert node.kwargs['package'] == 'gcp_stereo_ros'
    assert [eval(text.replace(repr('lifecycle'), value)) for value in ('true', 'false')] == [
        'gcp_stereo_lifecycle_node', 'gcp_stereo_node']  # noqa: S307 (the file's expression)
    assert node.kwargs['parameters'] == [
        fake['LaunchConfiguration']('params_file'),
        {'use_sim_time': fake['ParameterValue'](fake['LaunchConfiguration']('use_sim_time'),
                                                value_type=bool)}]


def test_a_start_up_value_for_an_unknown_name_stops_the_node(tmp_path):
    """`-p theta:=0.7` (a flat name of before) or a typo must not be ignored silently."""
    params = tmp_path / 'old.yaml'
    params.write_text('/**:\n  ros__parameters:\n    theta: 0.7\n')
    hint = "['theta'] (theta: each cost has its own, e.g. census.theta, sad.theta)"
    for args, says in ((['-p', 'theta:=0.7'], hint), (['--params-file', str(params)], hint),
                       (['-p', 'censu.P1:=3.0'],
                        "['censu.P1'] (did you mean 'census.P1'?); known: ")):
        proc = subprocess.run([sys.executable, '-m', 'gcp_stereo_ros.node', '--ros-args', *args],
                              capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2, proc.stderr
        line, = proc.stderr.strip().splitlines()
        assert line.startswith('gcp_stereo_node: error: cannot start: unknown parameter(s) '
                               + says), line
