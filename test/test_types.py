"""
The package's type annotations hold: mypy passes on the whole package, as setup.cfg says.

setup.cfg's [mypy] checks every module of gcp_stereo_ros; every function of stereo/ (its
cuda/ and cnn/ included), of evaluation/ and of the command line (tools/cli.py) is annotated
(disallow_untyped_defs), the rest is checked where it is annotated. Every console script's
main is annotated, which the second test finds.
"""
import ast
import configparser
from pathlib import Path
import re
import subprocess
import sys

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / 'gcp_stereo_ros'
# The modules whose every function is annotated, as setup.cfg's sections name them.
STRICT = ('gcp_stereo_ros.stereo.*', 'gcp_stereo_ros.evaluation.*', 'gcp_stereo_ros.tools.cli')


def _mypy_config():
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / 'setup.cfg')
    return cfg


def strict_sections():
    """Return {module pattern: disallow_untyped_defs} of setup.cfg's per-module sections."""
    cfg = _mypy_config()
    return {pattern.strip(): cfg[s].getboolean('disallow_untyped_defs')
            for s in cfg.sections() if s.startswith('mypy-')
            and cfg.has_option(s, 'disallow_untyped_defs')
            for pattern in s.removeprefix('mypy-').split(',')}


def module_name(path):
    """Return the dotted module name of a .py file of the package."""
    parts = path.relative_to(ROOT).with_suffix('').parts
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


def console_script_modules():
    """Return the files of the modules setup.py's console scripts run the main of."""
    names = re.findall(r"'[\w-]+ = ([\w.]+):main'", (ROOT / 'setup.py').read_text())
    assert len(names) >= 10, names
    paths = [ROOT / name.replace('.', '/') for name in names]
    return {p.with_suffix('.py') if p.with_suffix('.py').is_file() else p / '__init__.py'
            for p in paths}


def test_mypy_passes_on_the_whole_package():
    cfg = _mypy_config()
    assert [f.strip() for f in cfg['mypy']['files'].split(',')] == ['gcp_stereo_ros']
    assert not cfg.has_option('mypy', 'follow_imports'), 'every checked module is reported on'
    sections = strict_sections()
    assert all(sections.get(pattern) for pattern in STRICT), sections
    # no stereo module opts out of the annotations, nor out of the check
    stereo = [module_name(p) for p in sorted((PACKAGE / 'stereo').rglob('*.py'))]
    assert len(stereo) >= 25 and 'gcp_stereo_ros.stereo.cuda.sgm' in stereo, stereo
    for s in cfg.sections():
        patterns = s.removeprefix('mypy-').split(',')
        if s.startswith('mypy-') and any(p.startswith('gcp_stereo_ros.stereo') for p in patterns):
            assert cfg[s].getboolean('disallow_untyped_defs', True), s
            assert not cfg[s].getboolean('ignore_errors', False), s
    files = sorted(PACKAGE.rglob('*.py'))
    proc = subprocess.run([sys.executable, '-m', 'mypy'], cwd=ROOT, capture_output=True,
                          text=True, timeout=900)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    # every file of the package was checked, none skipped
    assert f'Success: no issues found in {len(files)} source files' in out, out


def test_every_console_script_main_is_annotated():
    mains = []
    for path in sorted(PACKAGE.rglob('*.py')):
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.FunctionDef) and node.name == 'main':
                mains.append(path)
                args = node.args.posonlyargs + node.args.args + node.args.kwonlyargs
                missing = [a.arg for a in args if a.annotation is None]
                assert not missing and node.returns is not None, (path, missing)
    # each console script's (gcp_stereo_node's main is ros/node.py's) and fit_confidence's
    assert console_script_modules() - {PACKAGE / 'node.py'} <= set(mains)
    assert len(mains) == 12, mains
