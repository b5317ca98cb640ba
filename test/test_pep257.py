"""ROS 2 lint convention (ament_python): docstrings checked by ament_pep257."""
from pathlib import Path

from ament_pep257.main import main
import pytest

ROOT = Path(__file__).resolve().parents[1]
CHECKED = ['gcp_stereo_ros', 'test', 'launch', 'doc', 'setup.py']


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257():
    rc = main(argv=[str(ROOT / p) for p in CHECKED])
    assert rc == 0, 'docstring style errors: see the output above'
