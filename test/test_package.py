"""
Packaging: the console scripts the README and the manual name are installed and behave.

Each installed script runs as a subprocess: exit status 0 on success, and on a user error
non-zero with one line on stderr that names the problem.
"""
from concurrent.futures import ThreadPoolExecutor
import importlib
import json
import os
from pathlib import Path
import re
import signal
import subprocess
import time

from gcp_stereo_ros.ros.graph import executable

ROOT = Path(__file__).resolve().parents[1]
# {console script: 'module:main'} as declared in setup.py
SCRIPTS = dict(re.findall(r"'([\w-]+) = (gcp_stereo_ros[.\w]+:main)'",
                          (ROOT / 'setup.py').read_text()))
# The scripts import this checkout, and find their installed metadata (importlib.metadata)
# on the inherited path.
ENV = {**os.environ, 'PYTHONPATH': os.pathsep.join(
    [str(ROOT), *filter(None, [os.environ.get('PYTHONPATH')])])}


def test_readme_commands_are_console_scripts():
    pattern = r'`(gcp-stereo-[\w-]+|gcp_stereo_node)`'
    named = set(re.findall(pattern, (ROOT / 'README.md').read_text()))
    assert len(named) >= 8 and named <= set(SCRIPTS), named - set(SCRIPTS)
    manual = {p.name: set(re.findall(pattern, p.read_text()))
              for p in (ROOT / 'doc').glob('*.md')}
    assert all(names <= set(SCRIPTS) for names in manual.values()), manual
    assert len(set().union(*manual.values())) >= 8, manual
    for target in SCRIPTS.values():
        module, _, func = target.partition(':')
        assert callable(getattr(importlib.import_module(module), func))


def call(script, *args, cwd):
    return subprocess.run([executable(script), *map(str, args)], env=ENV, cwd=cwd,
                          capture_output=True, text=True, timeout=120)


def call_all(calls, cwd):
    """Run (script, args) calls four at a time (most of their time is Python start-up)."""
    with ThreadPoolExecutor(4) as pool:
        return list(pool.map(lambda c: call(c[0], *c[1], cwd=cwd), calls))


def test_every_script_is_installed():
    assert len(SCRIPTS) == 11 and {'gcp_stereo_node', 'point_cloud_node',
                                   'gcp_stereo_lifecycle_node'} <= set(SCRIPTS)
    missing = [s for s in SCRIPTS if not executable(s).is_file()]
    assert not missing, f'not installed where `ros2 run` or pip puts them: {missing}'


def test_help_exits_0(tmp_path):
    for script, proc in zip(SCRIPTS, call_all([(s, ['--help']) for s in SCRIPTS], tmp_path)):
        assert proc.returncode == 0, (script, proc.stderr)
        assert script in proc.stdout and not proc.stderr, (script, proc.stdout, proc.stderr)


def test_eval_success_exits_0(tmp_path, kitti_occ_only):
    """A real evaluation exits 0; its table is followed by how the frame was scored."""
    rows = tmp_path / 'rows.json'
    proc = call('gcp-stereo-eval', '--dataset', kitti_occ_only, '--methods', 'opencv-sgbm',
                '--json', rows, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert 'Traceback' not in proc.stderr
    assert proc.stdout.splitlines()[-1] == (
        'note: kitti2015/000001_10: scored on disp_occ_0 (occluded pixels included): '
        'no disp_noc_0/000001_10.png'), proc.stdout
    (row,) = json.loads(rows.read_text())
    assert row['frame'] == 'kitti2015/000001_10' and 10 < row['bad3'] < 25, row


def failing_calls(tmp):
    """(script, arguments, text the error line must hold, exit status) of user errors."""
    missing = tmp / 'no_such_dataset'
    (tmp / 'a_file').write_text('')
    return [
        ('gcp-stereo-eval', ['--dataset', missing], missing, 1),
        ('gcp-stereo-bench', ['--dataset', missing], missing, 1),
        ('gcp-stereo-train', ['--dataset', missing, '--out', tmp / 'w.pt'], missing, 1),
        ('gcp-stereo-plot', ['sweep', '--dataset', missing, '--grid', 'theta=0.5'], missing, 1),
        ('gcp-stereo-plot', ['bars', '--json', tmp / 'a_file'], tmp / 'a_file', 1),
        ('gcp-stereo-bag', ['make', '--dataset', missing, '--out', tmp / 'bag'],
         f'{tmp / "bag"} not written', 1),
        ('gcp-stereo-load', ['--dataset', missing], missing, 1),
        ('gcp-stereo-batch', ['--dataset', missing], missing, 1),
        ('gcp-stereo-batch', ['--bags', missing, '--out', tmp / 'out'], missing, 1),
        ('gcp-stereo-load', ['-p', 'theta=0.5'], 'NAME:=VALUE', 2),
        ('gcp-stereo-demo', ['--out', tmp / 'a_file' / 'out'], tmp / 'a_file' / 'out', 1),
        ('gcp_stereo_node', ['--ros-args', '-p', 'max_disparity:=0'], 'max_disparity', 2),
        ('gcp_stereo_node', ['max_disparity:=64'], 'unrecognized arguments', 2),
    ]


def test_user_errors_exit_nonzero_with_one_line(tmp_path):
    calls = failing_calls(tmp_path)
    for (script, args, named, status), proc in zip(calls, call_all(calls, tmp_path)):
        # besides the usage lines argparse prints before its errors
        lines = [line for line in proc.stderr.splitlines() if not line.startswith(('usage:', ' '))]
        assert proc.returncode == status, (script, args, proc.returncode, proc.stderr)
        assert len(lines) == 1, (script, args, proc.stderr)
        assert lines[0].startswith(f'{script}: error: ') and str(named) in lines[0], lines


def test_node_exits_0_on_ctrl_c(tmp_path):
    log = tmp_path / 'node.log'
    with open(log, 'w') as stderr:
        node = subprocess.Popen(
            [executable('gcp_stereo_node'), '--ros-args', '-p', 'use_gcp:=false'],
            env=ENV, cwd=tmp_path, stderr=stderr)
    try:
        deadline = time.monotonic() + 60
        while 'ready' not in log.read_text() and node.poll() is None:
            assert time.monotonic() < deadline, log.read_text()
            time.sleep(0.1)
        node.send_signal(signal.SIGINT)
        assert node.wait(30) == 0, log.read_text()
    finally:
        if node.poll() is None:
            node.kill()
            node.wait()
