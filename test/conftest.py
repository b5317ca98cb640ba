"""Shared test set-up: where the real data lives, and an isolated ROS 2 graph per process."""
import os
from pathlib import Path

import pytest

# Every test process gets its own DDS domain on loopback only, so parallel runs never
# cross-talk; the shipped Fast DDS profile lets large images through shared memory.
REPO = Path(__file__).resolve().parents[1]
os.environ['ROS_DOMAIN_ID'] = str(1 + os.getpid() % 100)
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(REPO / 'config' / 'fastdds.xml')

DATA = REPO.parent / 'shared' / 'data'


@pytest.fixture(scope='session')
def data_dir():
    """`../shared/data` beside the checkout; CI always has it, so its absence fails loudly."""
    assert DATA.is_dir(), f'real test data expected at {DATA}'
    return DATA
