"""
The node's /diagnostics under a rig that drifts (stereo/drift.py), and the bag tool's.

A looped real pair, its right view moved a little further down and rolled each pass, then
set right again; a raw recording whose right camera moved, rectified and corrected at once.
"""
from diagnostic_msgs.msg import DiagnosticStatus
from gcp_stereo_ros.stereo.drift import ERROR, WARN
import numpy as np
import pytest
from rig import warp
from ros_helpers import wait_for

LEVELS = {DiagnosticStatus.OK: 'OK', DiagnosticStatus.WARN: 'WARN',
          DiagnosticStatus.ERROR: 'ERROR'}


@pytest.mark.parametrize('harness', [{'use_gcp': False, 'align_budget': 1.0}], indirect=True)
def test_a_drifting_rig_is_warned_then_an_error_then_ok_once_set_right(harness, pair):
    """
    0.3 px down and 0.01 degree more a pass, to 9 px; then undone: each level within 30.

    Each pass moves both views 1 px sideways (np.roll), so that no view shows as frozen.
    On a pair this small an estimate takes about as long as the pair (20-60 ms), so the
    budget lets them take all of the pairs' time: about one a pass, as a full-size pair on
    the CPU has with the default 5 %.
    """
    left, right = pair
    half = (left.shape[1] - 1) / 2
    stamp = iter(range(1_000_000_000, 100_000_000_000, 100_000_000))
    steps = [0.0] * 3 + list(np.arange(1, 31) * 0.3) + [9.0] * 10 + [0.0] * 15
    applied, levels, px = [], [], []
    for i, down in enumerate(steps):
        roll = down / 30
        applied.append(down + half * np.sin(np.radians(roll)))
        lv, rv = (np.roll(im, i, axis=1) for im in (left, warp(right, down, roll)))
        n = harness.node.stats.totals().processed
        harness.send_pair(lv, rv, 'rgb8', next(stamp))
        wait_for(lambda: harness.node.stats.totals().processed > n, 'the pair processed')
        status = harness.node.diagnostics.status()
        levels.append(LEVELS[status.level])
        px.append({kv.key: kv.value for kv in status.values}['misalignment px'])
    applied = np.array(applied)
    assert 'ERROR' not in levels[:3] and 'WARN' not in levels[:3], levels
    warned, failed = levels.index('WARN'), levels.index('ERROR')
    assert 0 <= warned - np.argmax(applied >= WARN) < 30, (levels, px)
    assert applied[warned] >= 0.9 * WARN and float(px[warned]) >= WARN
    assert 0 <= failed - np.argmax(applied > ERROR) < 30, (levels, px)
    undone = len(steps) - 15
    back = next(i for i in range(undone, len(steps)) if levels[i] == 'OK')
    assert back - undone < 30 and levels[back:] == ['OK'] * (len(steps) - back), (levels, px)
    assert float(px[-1]) < 0.25


def test_bag_run_folds_the_correction_into_the_rectification(tmp_path, distorted_pair, capsys):
    """
    A raw recording whose right camera moved 2 raw px down: each pair corrected, measured.

    Against the disparity of the rectified original over the interior, more than 1 px off:
    49 % with align false, 1.0 % with true (estimated 1.90 px, applied in the maps).
    """
    from bag_helpers import read_bag
    from gcp_stereo_ros.ros.params import config_from_params
    from gcp_stereo_ros.ros.rosimage import image_to_array
    from gcp_stereo_ros.stereo.pipeline import StereoPipeline
    from gcp_stereo_ros.tools import bag
    from test_bag_raw import raw_recording
    import yaml
    moved = warp(distorted_pair.raw['right'], 2.0, 0.0)
    recording = raw_recording(tmp_path / 'raw', type(distorted_pair)(
        **{**vars(distorted_pair), 'raw': {**distorted_pair.raw, 'right': moved}}))
    values = {'max_disparity': 32, 'use_gcp': False}
    original = StereoPipeline(config_from_params(values))(
        distorted_pair.rect['left'], distorted_pair.rect['right']).disparity
    inner = np.zeros(original.shape, bool)
    inner[12:-12, 32 + 12:-12] = True
    off = {}
    for align in (False, True):
        params = tmp_path / f'{align}.yaml'
        params.write_text(yaml.safe_dump({'/**': {'ros__parameters': {**values,
                                                                      'align': align}}}))
        out = tmp_path / f'out_{align}'
        assert bag.main(['run', '--in', str(recording), '--out', str(out), '--params',
                         str(params), '--rectify', '--outputs', 'disparity']) == 0
        disp_msg = read_bag(out)[0]['/cam/disparity'][-1][1]
        disp = image_to_array(disp_msg.image)
        disp[disp < disp_msg.min_disparity] = np.nan
        valid = inner & np.isfinite(disp) & np.isfinite(original)
        off[align] = (np.abs(disp - original)[valid] > 1).mean()
    printed = capsys.readouterr().out
    assert 'misalignment 1.' in printed and 'applied 1.' in printed, printed
    assert off[False] > 0.3 and off[True] < 0.05, off
