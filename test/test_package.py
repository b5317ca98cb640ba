"""Packaging: every command the README names is installed as a console script."""
import importlib
from pathlib import Path
import re

ROOT = Path(__file__).resolve().parents[1]


def test_readme_commands_are_console_scripts():
    scripts = dict(re.findall(r"'([\w-]+) = (gcp_stereo_ros[.\w]+:main)'",
                              (ROOT / 'setup.py').read_text()))
    named = set(re.findall(r'`(gcp-stereo-[\w-]+|gcp_stereo_node)`',
                           (ROOT / 'README.md').read_text()))
    assert len(named) >= 8 and named <= set(scripts), named - set(scripts)
    for target in scripts.values():
        module, _, func = target.partition(':')
        assert callable(getattr(importlib.import_module(module), func))
