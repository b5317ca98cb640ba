"""Shared test set-up: where the real data lives, and an isolated ROS 2 graph per process."""
import os
from pathlib import Path

from gcp_stereo_ros.ros.graph import private_env
import pytest

# Every test process gets its own DDS domain on loopback only, so parallel runs never
# cross-talk; the shipped Fast DDS profile lets large images through shared memory.
os.environ.update(private_env(1 + os.getpid() % 100))

DATA = Path(__file__).resolve().parents[2] / 'shared' / 'data'


@pytest.fixture(scope='session')
def data_dir():
    """`../shared/data` beside the checkout; CI always has it, so its absence fails loudly."""
    assert DATA.is_dir(), f'real test data expected at {DATA}'
    return DATA
