"""
The public API's type annotations hold: mypy passes on the modules setup.cfg names.

Those are StereoConfig, StereoPipeline, StereoResult and the stages' interface (every function
of their modules annotated), the evaluation functions, and every console script's main, which
the second test finds annotated.
"""
import ast
import configparser
from pathlib import Path
import re
import subprocess
import sys

ROOT = Path(__file__).resolve().parents[1]
# The public API's modules: each checked by mypy with every function annotated.
API = ('stereo/config.py', 'stereo/pipeline.py', 'stereo/stages.py', 'stereo/backend.py',
       'stereo/cnn/weights.py', 'evaluation/datasets.py', 'evaluation/metrics.py',
       'evaluation/viz.py')


def _mypy_config():
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / 'setup.cfg')
    return cfg


def checked_files():
    """Return the .py files that setup.cfg's mypy `files` names."""
    files = []
    for entry in _mypy_config()['mypy']['files'].split(','):
        path = ROOT / entry.strip()
        assert path.exists(), path
        files += sorted(path.rglob('*.py')) if path.is_dir() else [path]
    return files


def console_script_modules():
    """Return the files of the modules setup.py's console scripts run the main of."""
    names = re.findall(r"'[\w-]+ = ([\w.]+):main'", (ROOT / 'setup.py').read_text())
    assert len(names) >= 10, names
    paths = [ROOT / name.replace('.', '/') for name in names]
    return {p.with_suffix('.py') if p.with_suffix('.py').is_file() else p / '__init__.py'
            for p in paths}


def test_mypy_passes_on_the_public_api():
    files = checked_files()
    package = ROOT / 'gcp_stereo_ros'
    assert {package / m for m in API} <= set(files)
    assert console_script_modules() | {package / 'ros' / 'node.py'} <= set(files)
    strict = [s for s in _mypy_config().sections() if s.startswith('mypy-')
              and _mypy_config()[s].getboolean('disallow_untyped_defs', False)]
    patterns = ','.join(strict).replace('mypy-', '')
    for module in API:
        name = 'gcp_stereo_ros.' + module.removesuffix('.py').replace('/', '.')
        assert name in patterns or name.rpartition('.')[0] + '.*' in patterns, name
    proc = subprocess.run([sys.executable, '-m', 'mypy'], cwd=ROOT, capture_output=True,
                          text=True, timeout=900)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    # every file was checked, none skipped
    assert f'Success: no issues found in {len(files)} source files' in out, out


def test_every_console_script_main_is_annotated():
    mains = []
    for path in sorted((ROOT / 'gcp_stereo_ros').rglob('*.py')):
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.FunctionDef) and node.name == 'main':
                mains.append(path)
                args = node.args.posonlyargs + node.args.args + node.args.kwonlyargs
                missing = [a.arg for a in args if a.annotation is None]
                assert not missing and node.returns is not None, (path, missing)
    # each console script's (gcp_stereo_node's main is ros/node.py's) and fit_confidence's
    assert console_script_modules() - {ROOT / 'gcp_stereo_ros' / 'node.py'} <= set(mains)
    assert len(mains) == 12, mains
