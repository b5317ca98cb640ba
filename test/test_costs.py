"""The cost registry: a toy cost registered here runs through the pipeline, params and eval."""
import json
import subprocess
import sys

from gcp_stereo_ros.stereo.costs import COSTS, CostSpec, register
import pytest

# Registered before the node's parameters and the tools' methods are made, as a user's own
# cost module would be imported; everything after it is the package's own code.
TOY = '''
import json, sys
import cv2, numpy as np
from gcp_stereo_ros.stereo.costs import CostSpec, register


def absdiff_volume(left, right, max_disp, window, scale, invalid, out, cancel):
    """Mean |left - right| of gray levels / 255 over the window, per disparity slice."""
    h, w = left.shape
    r = window // 2
    out[:] = invalid
    for d in range(min(max_disp, w - 2 * r)):
        box = cv2.blur(np.abs(left[:, d:] - right[:, :w - d]) / 255, (window, window))
        out[r:h - r, d + r:w - r, d] = np.minimum(box[r:h - r, r:w - d - r] * scale, invalid)


register(CostSpec(
    name='absdiff', summary='box-filtered absolute difference', windows=(3, 15),
    top=lambda window: 1.0, standardized=False, integer=False, cpu=absdiff_volume, cuda=None,
    presets={'default': {'p1': 0.01, 'p2': 0.1, 'theta': 0.2, 'c_hi': 1.0, 'c_low': 0.0,
                         'gcp_lr_check': True, 'gcp_plain_check': False, 'plain_check': 0.0}}))

from gcp_stereo_ros import StereoConfig
from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.evaluation.metrics import error_rates
from gcp_stereo_ros.ros.params import BY_NAME, config_from_params
from gcp_stereo_ros.stereo.memory import volume_arithmetic
from gcp_stereo_ros.tools import evaluate

out = {'methods': list(evaluate.methods()), 'params': sorted(n for n in BY_NAME if 'absdiff' in n)}
config = config_from_params({'cost': 'absdiff', 'absdiff.P1': 0.02, 'absdiff.window': 7})
out['config'] = [config.cost, config.p1, config.window]
for bad in ({'absdiff.window': 17}, {'absdiff.P2': -1.0}):
    try:
        config_from_params(bad)
    except ValueError as err:
        out.setdefault('refused', []).append(str(err))
out['volume'] = str(volume_arithmetic(StereoConfig.for_cost('absdiff'))[1])
frame = load_frame(sys.argv[1], 'kitti2012/000070_10')
crop = (slice(100, 300), slice(300, 900))
runner = evaluate.Runner(paths=8)
for method in ('absdiff', 'absdiff+gcp', 'census'):
    result = runner.pipeline(method, 64)(frame.left[crop], frame.right[crop])
    out[method] = error_rates(result.disparity, frame.gt[crop])['bad3']
try:
    StereoConfig.for_cost('absdiff', device='cuda')
except ValueError as err:
    out['cuda'] = str(err)
print(json.dumps(out))
'''


@pytest.fixture(scope='module')
def toy(tmp_path_factory, data_dir):
    """Return what the toy cost's run reports (see TOY)."""
    script = tmp_path_factory.mktemp('toy') / 'toy.py'
    script.write_text(TOY)
    proc = subprocess.run([sys.executable, str(script), str(data_dir)], capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.splitlines()[-1])


def test_a_registered_cost_gets_its_methods_and_node_parameters(toy):
    assert {'absdiff', 'absdiff+gcp', 'census+gcp'} <= set(toy['methods'])
    assert toy['params'] == sorted(f'absdiff.{n}' for n in (
        'window', 'theta', 'P1', 'P2', 'c_hi', 'c_low', 'gcp_plain_check', 'plain_check'))
    assert toy['config'] == ['absdiff', 0.02, 7]
    window, p2 = toy['refused']
    assert 'absdiff.window must be in [3, 15]' in window and 'absdiff.P2' in p2
    assert toy['volume'] == 'float32'  # not an integer cost: no fixed point


def test_a_registered_cost_runs_through_the_pipeline_with_and_without_gcps(toy):
    # real errors on a real crop: the toy matches (far better than chance), the GCPs help it,
    # and Census stays ahead of a cost with no robustness to exposure
    assert 5 < toy['absdiff'] < 40, toy
    assert toy['absdiff+gcp'] < toy['absdiff'] - 1, toy
    assert toy['census'] < toy['absdiff'], toy
    assert "cost 'absdiff' has no CUDA kernel" in toy['cuda']


def test_a_cost_is_registered_once_with_usable_windows_and_defaults():
    spec = COSTS['census']
    with pytest.raises(ValueError, match="a cost named 'census' is registered already"):
        register(spec)
    with pytest.raises(ValueError, match='windows must be odd'):
        register(CostSpec('even', '', (4, 8), spec.top, False, True, spec.cpu, None,
                          spec.presets))
    with pytest.raises(ValueError, match='has no default preset values'):
        register(CostSpec('bare', '', (3, 5), spec.top, False, True, spec.cpu, None, {}))
    assert set(COSTS) == {'census', 'sad'}
