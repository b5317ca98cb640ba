"""The real-time preset: its values, its params file (the node, gcp-stereo-load), eval, errors."""
from pathlib import Path

from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.evaluation.metrics import error_rates
from gcp_stereo_ros.ros.params import config_from_params, load_params_file
from gcp_stereo_ros.stereo.config import StereoConfig
from gcp_stereo_ros.stereo.memory import memory_bytes, MIB
from gcp_stereo_ros.stereo.pipeline import StereoPipeline
from gcp_stereo_ros.tools import evaluate, load
import pytest
import yaml

REALTIME = Path(__file__).resolve().parents[1] / 'config' / 'gcp_stereo_realtime.yaml'


def test_the_params_file_is_the_preset():
    assert list(yaml.safe_load(REALTIME.read_text())) == ['/**']  # any name, any namespace
    config = config_from_params(load_params_file(REALTIME))
    assert config == StereoConfig.for_cost('census', 'realtime')
    default = StereoConfig()
    assert (config.downsample, config.paths, config.align) == (2, 4, False)
    # the rest is the default's: the CNN's filter, the GCP checks, plain SGM, invalidation
    assert config.replace(downsample=1, paths=16, align=True) == default


def test_sad_has_no_realtime_values():
    with pytest.raises(ValueError, match="preset 'realtime' has no values for cost 'sad'"):
        StereoConfig.for_cost('sad', 'realtime')


def test_eval_takes_the_presets_paths_unless_given():
    runner = evaluate.Runner(preset='realtime')
    assert runner.config('census+gcp', 128).paths == 4
    assert evaluate.Runner(8, preset='realtime').config('census+gcp', 128).paths == 8
    assert evaluate.Runner().config('census+gcp', 128).paths == 16  # the default's


def test_realtime_on_an_unseen_kitti_frame(data_dir):
    """KITTI 2012 000070, int8 where the CPU has VNNI: measured 6.22 % / 83.1 % / 2.51 %."""
    frame = load_frame(data_dir, 'kitti2012/000070_10')
    pipe = StereoPipeline(StereoConfig.for_cost('census', 'realtime', max_disp=frame.max_disp))
    result = pipe(frame.left, frame.right)
    rates = error_rates(result.disparity, frame.gt, frame.valid)
    assert 5.7 < rates['bad3'] < 6.8  # full size 4.3, OpenCV MODE_SGBM_3WAY 7.34
    assert 81 < rates['density'] < 85 and rates['bad3_published'] < 3.0
    assert 'align' not in result.seconds and 'plain_sgm' in result.seconds


def test_load_reads_a_params_file(capsys):
    """gcp-stereo-load --params: the realtime file's memory estimate, not the default's."""
    assert load.main(['--steps', '640x480:64', '--pipeline', '--params', str(REALTIME)]) == 0
    row = capsys.readouterr().out.splitlines()[-1].split()
    estimate = memory_bytes(StereoConfig.for_cost('census', 'realtime', max_disp=64), 480, 640)
    assert row[0] == '640x480:64' and int(row[2]) == round(estimate / MIB)
    assert estimate < memory_bytes(StereoConfig(max_disp=64), 480, 640) / 2
