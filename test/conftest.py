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


@pytest.fixture
def kitti_occ_only(tmp_path, data_dir):
    """
    Build a KITTI 2015 folder whose frame 000001_10 has disp_occ_0 but no disp_noc_0.

    Frame 000002_10 has images and no ground truth at all. Files link to the shared data.
    """
    shared = data_dir / 'kitti2015' / 'training'
    training = tmp_path / 'kitti2015' / 'training'
    for sub, stems in (('image_2', ('000001_10', '000002_10')),
                       ('image_3', ('000001_10', '000002_10')), ('disp_occ_0', ('000001_10',))):
        (training / sub).mkdir(parents=True)
        for stem in stems:
            (training / sub / f'{stem}.png').symlink_to(shared / sub / f'{stem}.png')
    return tmp_path
