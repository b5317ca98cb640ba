"""ROS 2 lint convention (ament_python): flake8 with ament's settings, line length 99."""
from pathlib import Path

from ament_flake8.main import main_with_errors
import pytest

ROOT = Path(__file__).resolve().parents[1]
CHECKED = ['gcp_stereo_ros', 'test', 'launch', 'doc', 'setup.py']


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8():
    rc, errors = main_with_errors(argv=[str(ROOT / p) for p in CHECKED])
    assert rc == 0, f'{len(errors)} flake8 error(s):\n' + '\n'.join(errors)
