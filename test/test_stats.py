"""NodeStats: counters and samples read without changing them, and whether to trust the depth."""
import threading

from diagnostic_msgs.msg import DiagnosticStatus
from gcp_stereo_ros.ros.stats import LEVEL_PAIRS, NodeStats, Sample, trust
from gcp_stereo_ros.ros.worker import NewestWorker
from gcp_stereo_ros.stereo.health import Finding
import numpy as np
import pytest
from ros_helpers import wait_for

BLACK = Finding('black', 'right view black')
DARKER = Finding('exposure', 'exposures far apart (right darker)')


def samples(shares, start=0, **fields):
    """Return Samples a second apart from `start`, of `shares`, confidence 0.9."""
    return [Sample(float(start + i), 0.5, share, 0.9, **fields) for i, share in enumerate(shares)]


def test_totals_and_samples_are_read_without_change():
    stats = NodeStats()
    for sample in samples([0.8, 0.7, 0.6]):
        stats.pair_done(sample, {'cnn': 0.25, 'sgm': 0.5})
    stats.error('skipping pair: too small')
    stats.dropped_stale()
    stats.dropped_stale()
    for _ in range(2):  # reading twice gives the same
        totals = stats.totals()
        assert totals[:4] == (3, 1, 2, 'skipping pair: too small')
        assert totals.stage_seconds == {'cnn': 0.75, 'sgm': 1.5}
        assert [s.share for s in stats.samples(since=0.5)] == [0.7, 0.6]
        assert len(stats.samples()) == 3
    totals.stage_seconds['cnn'] = 9.0  # a snapshot: changing it changes nothing kept
    assert stats.totals().stage_seconds['cnn'] == 0.75


def test_steady_depth_is_trusted_with_its_running_level():
    got = trust(samples([0.8] * 20))
    assert (got.share, got.share_level) == (pytest.approx(0.8), 0.8)
    assert (got.confidence, got.confidence_level) == (pytest.approx(0.9), 0.9)
    assert (got.warning, got.cause, got.misalignment, got.misalignment_note) == (
        '', '', None, 'not estimated')
    early = trust(samples([0.8] * 9))  # 4 pairs before the recent 5: no level yet
    assert early.share_level is None and not early.warning


def test_a_collapse_against_the_running_level_is_warned_with_its_cause():
    steady = samples([0.8] * 20)
    two = trust(steady + samples([0.1] * 2, 20))  # recent mean 0.52: not yet below 0.4
    assert two.share == pytest.approx(0.52) and not two.warning
    got = trust(steady + samples([0.1] * 3, 20))  # recent mean 0.38 < 0.4
    assert got.warning == ('depth not to be trusted: published share of the valid window '
                           '0.38 against its running level 0.80; cause: not seen')
    named = trust(steady + samples([0.1] * 3, 20, findings=(DARKER,), misalignment=1.23))
    assert named.cause == 'exposures far apart (right darker); rows misaligned by up to 1.23 px'
    assert named.views == (DARKER,) and named.misalignment == 1.23
    drop = trust(steady + [s._replace(confidence=0.2) for s in samples([0.8] * 5, 20)])
    assert drop.warning == ('depth not to be trusted: disparity confidence 0.20 against its '
                            'running level 0.90; cause: not seen')


def test_a_lasting_change_ends_the_warning_within_half_the_level_pairs():
    steady = samples([0.8] * LEVEL_PAIRS)
    assert trust(steady + samples([0.1] * 50, LEVEL_PAIRS)).warning
    assert not trust(steady + samples([0.1] * 57, LEVEL_PAIRS)).warning


def test_a_fault_in_each_of_the_last_three_pairs_is_warned_at_once():
    first = samples([0.8])  # no running level: only the fault can say it
    assert not trust(first + samples([0.05] * 2, 1, findings=(BLACK,))).warning
    got = trust(first + samples([0.05] * 3, 1, findings=(BLACK,)))
    assert got.warning == ('depth not to be trusted: right view black in each of the last 3 '
                           'pairs; cause: right view black')
    assert got.cause == 'right view black'
    gap = samples([0.05] * 3, 1, findings=(BLACK,))
    gap[1] = gap[1]._replace(findings=())
    assert not trust(first + gap).warning
    assert not trust(first + samples([0.8] * 3, 1, findings=(DARKER,))).warning  # no fault


def test_the_worker_reports_a_replaced_item_as_stale():
    started, release, done, stale = threading.Event(), threading.Event(), [], []

    def process(x):
        started.set()
        release.wait(10)
        done.append(x)
    worker = NewestWorker(process, 'test_stale', on_error=print, on_stale=lambda: stale.append(1))
    worker.put((1,))
    assert started.wait(5)
    worker.put((2,))
    worker.put((3,))  # replaces 2, which was still waiting
    assert (stale, worker.idle) == ([1], False)
    release.set()
    wait_for(lambda: worker.idle, 'the worker idle', 5)
    assert done == [1, 3] and stale == [1] and worker.stop(5)


@pytest.mark.parametrize('harness', [{'use_gcp': False, 'log_every_n_frames': 10}],
                         indirect=True)
def test_a_black_then_frozen_right_view_is_warned_and_named_within_ten_pairs(harness, pair):
    """Real pairs (each moved by a pixel, so no view repeats) are trusted; failures named."""
    left, right = pair
    stamp = iter(range(1_000_000_000, 100_000_000_000, 100_000_000))

    def send(lv, rv):
        n = harness.node.stats.totals().processed
        harness.send_pair(lv, rv, 'rgb8', next(stamp))
        wait_for(lambda: harness.node.stats.totals().processed > n, 'the pair processed')
        return harness.node.diagnostics.status()

    def values(status):
        return {kv.key: kv.value for kv in status.values}

    def good(i):
        return np.roll(left, i, axis=1), np.roll(right, i, axis=1)
    for i in range(10):
        status = send(*good(i))
    got = values(status)
    assert status.level == DiagnosticStatus.OK, status.message
    assert 0.5 < float(got['published share of valid window']) < 1
    assert float(got['published share of valid window, running level']) > 0.5
    assert (got['view check'], got['cause']) == ('ok', '')
    assert float(got['misalignment px']) < 0.25  # Motorcycle: aligned (stereo/drift.py)
    progress = [m for m in harness.error_logs('INFO') if 'pairs processed' in m]
    assert len(progress) == 1 and progress[0].startswith(
        '10 pairs processed; last 10: ms per stage align 0, cost '), progress
    assert 'dropped stale 0, unmatched left 0 right 0, errors 0' in progress[0]
    for n in range(1, 11):
        status = send(good(10 + n)[0], np.zeros_like(right))
        if status.level == DiagnosticStatus.WARN:
            break
    assert 'right view black' in status.message and n <= 3, (n, status.message)
    assert values(status)['cause'] == 'right view black'
    for i in range(20, 26):  # good again: trusted once the recent pairs are
        status = send(*good(i))
    assert status.level == DiagnosticStatus.OK, status.message
    for n in range(1, 11):
        status = send(good(30 + n)[0], right)
        if status.level == DiagnosticStatus.WARN:
            break
    assert 'right view frozen' in status.message and n <= 4, (n, status.message)
