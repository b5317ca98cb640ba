"""
The misalignment over frames: smoothing, jumps, levels, the cadence and the background thread.

The last test drifts the right view of a real pair frame by frame, as a rig that loosens:
the level must turn WARN, then ERROR, within 30 frames of the drift crossing each level, and
OK again once the drift is undone.
"""
import time

from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.stereo.alignment import estimate, Misalignment
from gcp_stereo_ros.stereo.drift import Background, Cadence, DriftTracker, ERROR, Monitor, WARN
import numpy as np
import pytest
from rig import warp

SHAPE = (375, 1242)


def known(offset, roll=0.0, error=0.02):
    """Return a known estimate of `offset` and `roll` px, each with standard error `error`."""
    return Misalignment(True, (offset, roll, 0.0, 0, 0, 0), (error, error, error, 0, 0, 0),
                        SHAPE, 300, 0.2, error)


def test_the_estimates_are_weighed_by_their_errors():
    t = DriftTracker()
    assert not t.current.known and t.status().px is None
    assert t.status().message == 'no estimate yet' and not t.correction().known
    for _ in range(5):
        t.update(known(0.6))
    t.update(known(0.9, error=0.3))  # unsure: moves it by a few hundredths only
    assert 0.6 < t.current.term('offset') < 0.62
    t.update(known(0.7))  # as sure as the others: pulls it the more
    assert 0.63 < t.current.term('offset') < 0.66
    assert t.current.errors[0] < 0.02 and t.correction().known


def test_a_single_wrong_estimate_changes_nothing_and_a_jump_restarts():
    t = DriftTracker()
    for _ in range(4):
        t.update(known(0.3))
    t.update(known(2.0))  # one stray estimate: held, not used
    assert t.current.term('offset') == pytest.approx(0.3)
    t.update(known(0.3))
    t.update(known(3.0))
    t.update(known(3.1))  # the rig moved: restarted from the two
    assert 3.05 < t.current.term('offset') < 3.06 and t.estimates == 2


def test_unknown_estimates_keep_the_last_known_one():
    t = DriftTracker()
    t.update(Misalignment(False, shape=SHAPE, reason='dark: 3 matches, fewer than 40',
                          cause='dark'))
    assert t.status().message == 'dark: 3 matches, fewer than 40'
    t.update(known(0.5))
    t.update(Misalignment(False, shape=SHAPE, reason='textureless', cause='textureless'))
    status = t.status()
    assert status.level == 'OK' and status.px == pytest.approx(0.5)
    assert 'last 1 estimates unknown: textureless' in status.message


@pytest.mark.parametrize('offset, level, corrected', [
    (0.1, 'OK', False), (0.5, 'OK', True), (WARN + 0.2, 'WARN', True),
    (ERROR + 1, 'ERROR', False)])
def test_the_levels(offset, level, corrected):
    t = DriftTracker()
    t.update(known(offset))
    assert t.status().level == level and t.status().px == pytest.approx(offset)
    assert t.correction().known == corrected


def test_the_cadence_keeps_the_estimates_within_their_share():
    """A 0.1 s frame, a 0.03 s estimate and a 0.002 s correction: 5 % of the time in all."""
    c = Cadence(0.05)
    runs = 0
    for _ in range(1000):
        if c.due():
            c.spent(0.03)
            runs += 1
        c.frame(0.1, 0.002)
    cost = runs * 0.03 + 1000 * 0.002
    assert 0.045 < cost / 100 <= 0.05 + 0.03 / 100  # 100 s of frames; one estimate ahead
    c = Cadence(0.05)
    assert c.due()
    c.spent(0.03)
    for _ in range(100):  # an idle spell of long frames: no burst after it
        c.frame(10.0)
    c.spent(0.03)
    c.spent(0.03)
    assert not c.due()


@pytest.fixture(scope='module')
def cones(data_dir):
    """Middlebury cones, a validation frame within 0.08 px of aligned."""
    return load_frame(data_dir, 'middlebury_v2/cones')


def test_the_background_thread_gives_the_estimate(cones):
    b = Background()
    try:
        assert b.collect() is None and not b.busy
        assert b.submit(cones.left, cones.right, cones.max_disp)
        assert not b.submit(cones.left, cones.right, cones.max_disp) and b.busy
        deadline = time.monotonic() + 30
        while (done := b.collect()) is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert done is not None and not b.busy
        m, seconds = done
        assert m == estimate(cones.left, cones.right, cones.max_disp) and 0 < seconds < 30
    finally:
        b.close()


def test_the_monitor_estimates_in_the_background_and_corrects(cones):
    """Cones moved 2 px down: the first pairs as they are, then corrected; align off: None."""
    from gcp_stereo_ros.stereo.config import StereoConfig
    config = StereoConfig(max_disp=cones.max_disp)
    moved = warp(cones.right, 2.0, 0.0)
    m = Monitor()
    try:
        first = m.before(cones.left, moved, config, {})
        assert not first.known and m.status().message == 'no estimate yet'
        deadline = time.monotonic() + 30
        while not m.tracker.estimates and time.monotonic() < deadline:
            m.after(0.0)
            time.sleep(0.05)
            given = m.before(cones.left, moved, config, {'align_warn_px': 1.5})
        assert given.known and abs(given.term('offset') - 1.92) < 0.05
        assert m.status().level == 'WARN' and 'the rig has drifted' in m.status().message
        assert m.before(cones.left, moved, config.replace(align=False), {}) is None
        assert m.status().message == 'align is off'
    finally:
        m.close()
    refused = Monitor()
    try:
        with pytest.raises(ValueError, match='one size'):
            refused.before(cones.left, moved[:50], config, {})
        assert not refused.background.busy
    finally:
        refused.close()
    inline = Monitor(every=True)
    assert inline.before(cones.left, moved, config, {}).known and inline.tracker.estimates == 1


def test_a_drifting_rig_turns_warn_then_error_then_ok_once_undone(cones):
    """Down by 0.15 px and rolled by 0.005 degree more each frame, to 9 px; then undone."""
    half = (cones.left.shape[1] - 1) / 2
    t = DriftTracker()
    applied, levels = [], []
    steps = [0.0] * 5 + list(np.arange(1, 61) * 0.15) + [9.0] * 20 + [0.0] * 20
    for down in steps:
        roll = down / 30
        applied.append(down + half * np.sin(np.radians(roll)))
        t.update(estimate(cones.left, warp(cones.right, down, roll), cones.max_disp))
        levels.append(t.status().level)
    applied = np.array(applied)
    first = {lv: levels.index(lv) for lv in ('WARN', 'ERROR')}
    assert levels[:5] == ['OK'] * 5
    assert applied[first['WARN']] >= WARN * 0.9
    assert first['WARN'] - np.argmax(applied >= WARN) < 30
    assert applied[first['ERROR']] >= ERROR * 0.9
    assert first['ERROR'] - np.argmax(applied >= ERROR) < 30
    undone = len(steps) - 20
    assert levels[undone + 5:] == ['OK'] * 15  # a jump: two estimates to restart
    assert t.current.largest < 0.15
