"""StampSync: exact and approximate matching by stamp, drops, the unmatched streak; CameraInfos."""
import math

from gcp_stereo_ros.ros.sync import CameraInfos, image_sync, SIDES, StampSync, tolerance_ns
import pytest

MS = 1_000_000  # nanoseconds


def pair_sync(queue_size=10, approximate=False, tolerance=0.0, max_bytes=None):
    """Return the node's sync of left and right images, as image_sync builds it."""
    return StampSync(SIDES, queue_size, tolerance_ns(approximate, tolerance), max_bytes)


def test_exact_pairs_identical_stamps_in_either_order():
    sync = pair_sync()
    assert sync.add('left', 100, 'L100') is None
    assert sync.add('right', 100, 'R100') == {'left': 'L100', 'right': 'R100'}
    assert sync.add('right', 200, 'R200') is None
    assert sync.add('left', 200, 'L200') == {'left': 'L200', 'right': 'R200'}
    assert (sync.sets, sync.dropped['left'], sync.dropped['right']) == (2, 0, 0)


def test_exact_drops_and_counts_unmatched_stamps():
    sync = pair_sync()
    assert sync.add('left', 100, 'L100') is None
    assert sync.add('right', 101, 'R101') is None  # 1 ns apart: not exact
    assert sync.add('left', 200, 'L200') is None
    assert sync.add('right', 200, 'R200') == {'left': 'L200', 'right': 'R200'}
    assert (sync.sets, sync.dropped['left'], sync.dropped['right']) == (1, 1, 1)
    # Older than the emitted pair, from one side only: a straggler, dropped at the next pair.
    assert sync.add('left', 101, 'L101') is None
    assert sync.add('left', 300, 'L300') is None
    assert sync.add('right', 300, 'R300') == {'left': 'L300', 'right': 'R300'}
    assert (sync.sets, sync.dropped['left'], sync.dropped['right']) == (2, 2, 1)


def test_exact_out_of_order_arrival():
    sync = pair_sync()
    assert sync.add('left', 300, 'L300') is None
    assert sync.add('left', 100, 'L100') is None
    assert sync.add('right', 200, 'R200') is None
    assert sync.add('right', 100, 'R100') == {'left': 'L100', 'right': 'R100'}
    assert sync.add('left', 200, 'L200') == {'left': 'L200', 'right': 'R200'}
    assert sync.add('right', 300, 'R300') == {'left': 'L300', 'right': 'R300'}
    assert (sync.sets, sync.dropped['left'], sync.dropped['right']) == (3, 0, 0)


def test_exact_queue_overflow_drops_oldest_stamp():
    sync = pair_sync(queue_size=3)
    for stamp in (400, 100, 300, 200):  # 4 > 3: stamp 100 goes although it came second
        assert sync.add('left', stamp, f'L{stamp}') is None
    assert sync.dropped['left'] == 1
    assert sync.add('right', 100, 'R100') is None
    assert sync.add('right', 200, 'R200') == {'left': 'L200', 'right': 'R200'}
    # R100 discarded by the pair
    assert (sync.sets, sync.dropped['left'], sync.dropped['right']) == (1, 1, 1)


def test_pair_discards_everything_older_on_both_sides():
    sync = pair_sync()
    for stamp in (100, 200, 400):
        sync.add('left', stamp, f'L{stamp}')
    for stamp in (150, 250):
        sync.add('right', stamp, f'R{stamp}')
    assert sync.add('right', 400, 'R400') == {'left': 'L400', 'right': 'R400'}
    assert (sync.dropped['left'], sync.dropped['right']) == (2, 2)
    assert sync.add('left', 250, 'L250') is None  # R250 was discarded
    assert sync.add('left', 500, 'L500') is None
    assert sync.add('right', 500, 'R500') == {'left': 'L500', 'right': 'R500'}
    assert sync.dropped['left'] == 3  # L250, a straggler, at this pair


def test_exact_ignores_tolerance():
    sync = pair_sync(approximate=False, tolerance=1.0)
    sync.add('left', 100, 'L')
    assert sync.add('right', 101, 'R') is None


def test_approximate_pairs_within_tolerance_only():
    sync = pair_sync(approximate=True, tolerance=0.005)
    assert sync.add('left', 1000 * MS, 'L1') is None
    # exactly at the tolerance
    assert sync.add('right', 1005 * MS, 'R1') == {'left': 'L1', 'right': 'R1'}
    assert sync.add('left', 2000 * MS, 'L2') is None
    assert sync.add('right', 2005 * MS + 1, 'R2') is None  # 1 ns beyond it
    assert sync.add('right', 1997 * MS, 'R3') == {'left': 'L2', 'right': 'R3'}
    # R2 is newer: still queued
    assert (sync.sets, sync.dropped['left'], sync.dropped['right']) == (2, 0, 0)


def test_approximate_chooses_closest_match():
    sync = pair_sync(approximate=True, tolerance=0.010)
    sync.add('left', 100 * MS, 'L100')
    sync.add('left', 106 * MS, 'L106')
    sync.add('left', 111 * MS, 'L111')
    assert sync.add('right', 108 * MS, 'R108') == {'left': 'L106', 'right': 'R108'}
    assert sync.dropped['left'] == 1  # L100; L111 may still pair
    assert sync.add('right', 112 * MS, 'R112') == {'left': 'L111', 'right': 'R112'}


def test_approximate_tie_keeps_the_newer_candidate():
    sync = pair_sync(approximate=True, tolerance=0.010)
    sync.add('left', 100 * MS, 'L100')
    sync.add('left', 106 * MS, 'L106')
    assert sync.add('right', 103 * MS, 'R103') == {'left': 'L100', 'right': 'R103'}
    assert sync.add('right', 107 * MS, 'R107') == {'left': 'L106', 'right': 'R107'}
    assert sync.dropped['left'] == 0


def test_approximate_out_of_order_arrival():
    sync = pair_sync(approximate=True, tolerance=0.002)
    assert sync.add('right', 301 * MS, 'R301') is None
    assert sync.add('right', 101 * MS, 'R101') is None
    assert sync.add('left', 200 * MS, 'L200') is None
    assert sync.add('left', 100 * MS, 'L100') == {'left': 'L100', 'right': 'R101'}
    assert sync.add('left', 300 * MS, 'L300') == {'left': 'L300', 'right': 'R301'}
    # L200 never got a twin
    assert (sync.sets, sync.dropped['left'], sync.dropped['right']) == (2, 1, 0)


def test_unmatched_streak_grows_while_one_side_is_missing():
    sync = pair_sync(queue_size=2)
    for i in range(6):  # the right images of 6 frames are lost
        sync.add('left', i, f'L{i}')
    assert sync.unmatched_streak('left') == 4
    assert sync.unmatched_streak('right') == 0
    sync.add('right', 3, 'R3')  # older than queued L4, L5: kept
    assert sync.unmatched_streak('right') == 0
    assert sync.add('right', 5, 'R5') == {'left': 'L5', 'right': 'R5'}
    assert (sync.dropped['left'], sync.dropped['right']) == (5, 1)
    assert sync.unmatched_streak('left') == sync.unmatched_streak('right') == 0
    sync.add('right', 4, 'R4')  # older than the pair: dropped at the next one
    sync.add('left', 6, 'L6')
    assert sync.add('right', 6, 'R6') == {'left': 'L6', 'right': 'R6'}
    assert sync.dropped['right'] == 2 and sync.unmatched_streak('right') == 0


@pytest.mark.parametrize('kwargs, reason', [
    ({'queue_size': 0}, 'queue_size'),
    ({'queue_size': 2.5}, 'queue_size'),
    ({'queue_size': True}, 'queue_size'),
    ({'tolerance': -0.1}, 'tolerance'),
    ({'tolerance': float('nan')}, 'tolerance'),
    ({'tolerance': float('inf')}, 'tolerance'),
])
def test_rejects_bad_arguments(kwargs, reason):
    with pytest.raises(ValueError, match=reason):
        pair_sync(**kwargs)


def test_rejects_unknown_side():
    sync = pair_sync()
    with pytest.raises(ValueError, match="no topic 'center'; the topics: 'left', 'right'"):
        sync.add('center', 0, None)
    with pytest.raises(ValueError, match="no topic 'Left'"):
        sync.unmatched_streak('Left')


def test_stream_restart_starts_pairing_afresh():
    sync = pair_sync()
    assert sync.add('left', 50_000_000_000, 'l1') is None
    assert sync.add('right', 50_000_000_000, 'r1') == {'left': 'l1', 'right': 'r1'}
    assert sync.add('left', 49_900_000_000, 'late') is None  # one side back: a straggler
    assert sync.add('left', 1_000_000_000, 'l2') is None  # it replaces the straggler
    assert sync.dropped['left'] == 1
    assert sync.add('right', 1_000_000_000, 'r2') == {'left': 'l2', 'right': 'r2'}  # both back


@pytest.mark.parametrize('approximate', [False, True])
def test_looped_one_frame_bag_pairs_on_every_pass(approximate):
    """A one-frame bag played with --loop repeats one stamp: every pass is a pair."""
    sync = pair_sync(approximate=approximate, tolerance=0.01)
    for n in range(1, 6):
        assert sync.add('left', 7 * MS, f'L{n}') is None
        assert sync.add('right', 7 * MS, f'R{n}') == {'left': f'L{n}', 'right': f'R{n}'}
    assert (sync.sets, sync.dropped['left'], sync.dropped['right']) == (5, 0, 0)


def test_looped_short_bag_pairs_every_frame_of_every_pass():
    """Three frames 0.1 s apart, looped: each pass starts 0.2 s before the last pair."""
    sync = pair_sync()
    got = []
    for _ in range(4):
        for stamp in (0, 100 * MS, 200 * MS):
            for side in ('left', 'right'):
                pair = sync.add(side, stamp, stamp)
                if pair is not None:
                    got.append(pair['left'])
    assert got == [0, 100 * MS, 200 * MS] * 4
    assert (sync.dropped['left'], sync.dropped['right']) == (0, 0)


def test_queues_are_bounded_in_bytes_too():
    sync = pair_sync(queue_size=100, max_bytes=250)
    for i in range(5):
        assert sync.add('left', i, f'L{i}', 100) is None
    assert sync.dropped['left'] == 3  # two 100-byte images fit in 250 bytes
    assert sync.add('right', 4, 'R4', 100) == {'left': 'L4', 'right': 'R4'}
    assert sync.add('right', 9, 'big', 1000) is None  # the newest is kept, whatever its size
    assert sync.add('left', 9, 'L9', 100) == {'left': 'L9', 'right': 'big'}


def test_the_policies_of_more_topics():
    exact = StampSync('abc', queue_size=2)
    assert exact.add('a', 10, 'a10') is None and exact.add('b', 10, 'b10') is None
    assert exact.add('c', 11, 'c11') is None  # no 11 elsewhere
    assert exact.add('c', 10, 'c10') == {'a': 'a10', 'b': 'b10', 'c': 'c10'}
    assert exact.dropped == {'a': 0, 'b': 0, 'c': 0} and exact.add('a', 12, 'a12') is None
    for stamp in (13, 14):  # queue_size 2: a12 goes
        exact.add('a', stamp, f'a{stamp}')
    assert exact.dropped == {'a': 1, 'b': 0, 'c': 0}
    close = StampSync('ab', tolerance_ns=tolerance_ns(True, 0.002))  # ApproximateEpsilonTime
    assert close.add('a', 1_000_000, 1) is None and close.add('b', 4_000_000, 2) is None
    assert close.add('b', 2_500_000, 3) == {'a': 1, 'b': 3}
    assert close.dropped == {'a': 0, 'b': 0}  # b at 4 ms is newer than the set: it waits
    closest = StampSync('ab', tolerance_ns=tolerance_ns(True, 0.0))  # ApproximateTime
    assert closest.tolerance_ns == math.inf and tolerance_ns(False, 0.5) == 0
    assert closest.add('a', 0, 'a0') is None and closest.add('b', 3, 'b3') is None  # no period
    assert closest.add('a', 10, 'a10') is None  # period 10: at most 4 apart
    assert closest.add('b', 13, 'b13') == {'a': 'a10', 'b': 'b13'}
    assert closest.dropped == {'a': 1, 'b': 1}


def test_three_topics_go_back_in_time_together():
    """point_cloud_node's inputs from a looped bag: a set on every pass."""
    sync = StampSync('abc')
    for n in range(3):
        assert sync.add('a', 5, f'a{n}') is None and sync.add('b', 5, f'b{n}') is None
        assert sync.add('c', 5, f'c{n}') == {'a': f'a{n}', 'b': f'b{n}', 'c': f'c{n}'}
    assert sync.sets == 3 and sync.dropped == {'a': 0, 'b': 0, 'c': 0}


def test_approximate_sync_without_a_tolerance_pairs_the_closest_stamps():
    """As stereo_image_proc: approximate_sync with tolerance 0 is ApproximateTime."""
    sync = image_sync({'approximate_sync': True})
    assert sync.tolerance_ns == math.inf
    got = []
    for k in range(8):  # 30 Hz, the right camera 7 ms late; left frame 2, right frame 5 lost
        for side, stamp in (('left', 33 * k), ('right', 33 * k + 7)):
            if (side, k) not in {('left', 2), ('right', 5)}:
                pair = sync.add(side, stamp * MS, stamp)
                if pair is not None:
                    got.append((pair['left'], pair['right']))
    # within half the frame period, known from the second image of a side on
    assert got == [(33, 40), (99, 106), (132, 139), (198, 205), (231, 238)]
    assert sync.dropped == {'left': 2, 'right': 2}  # L0, R7 (no period yet); L165, R73
    assert sync.flush() is None
    assert image_sync({'approximate_sync': False}).tolerance_ns == 0
    assert image_sync({'approximate_sync': True,
                      'approximate_sync_tolerance_seconds': 0.01}).tolerance_ns == 10 * MS
    # the camera_info of an image: its own stamp, as the driver gives them
    assert CameraInfos(sync.tolerance_ns).tolerance_ns == 0


def test_closest_stamps_skipped_images_and_one_frame():
    """A node that keeps only the newest image: the period per image its publisher sent."""
    sync = image_sync({'approximate_sync': True})
    assert sync.add('left', 0, 0) is None and sync.add('right', 7 * MS, 0) is None
    # 30 frames later, the right image before the newest left one: a frame apart, no pair
    assert sync.add('right', (33 * 30 + 7) * MS, 30, sent=30) is None
    assert sync.add('left', 33 * 31 * MS, 31, sent=31) is None
    assert sync.add('right', (33 * 31 + 7) * MS, 31) == {'left': 31, 'right': 31}
    # no sequence numbers (sent None): no period, identical stamps only
    blind = image_sync({'approximate_sync': True})
    for k in range(3):
        blind.add('left', 33 * k * MS, k, sent=None)
        assert blind.add('right', (33 * k + 7) * MS, k, sent=None) is None
    # a copy 1 ns later counted as two images: the median of the gaps gets over it
    copy = image_sync({'approximate_sync': True})
    got = []
    for k, stamp in enumerate([0, 1, 33, 66, 99]):
        copy.add('left', stamp * MS + (k == 1), stamp, sent=2 if k == 1 else 1)
        pair = copy.add('right', (stamp + 7) * MS, stamp)
        got.append(pair and pair['left'])
    assert got == [None, None, None, 66, 99]
    one = image_sync({'approximate_sync': True})  # a recording of one frame
    assert one.add('left', 0, 'L') is None and one.add('right', 7 * MS, 'R') is None
    assert one.flush() == {'left': 'L', 'right': 'R'} and one.flush() is None
    assert image_sync({}).flush() is None


@pytest.mark.parametrize('lost', ['left', 'right'])
def test_closest_stamps_recover_from_a_lost_image(lost):
    """Identical stamps, left first: after a lost image the pairs are again of one frame."""
    sync = image_sync({'approximate_sync': True})
    got = []
    for k in range(6):
        for side in SIDES:
            if (side, k) != (lost, 1):
                pair = sync.add(side, 33 * k * MS, (side, k))
                if pair is not None:
                    got.append((pair['left'][1], pair['right'][1]))
    assert got == [(0, 0), (2, 2), (3, 3), (4, 4), (5, 5)]
    assert sync.dropped == {'left': lost == 'right', 'right': lost == 'left'}


def test_node_queues_hold_a_quarter_of_the_memory_limit():
    assert image_sync({'queue_size': 1000, 'memory_limit_mb': 3072}).max_bytes == 768 << 20


def test_camera_infos_pair_each_image_with_its_own_stamp():
    infos = CameraInfos(tolerance_ns=5, keep=3)
    assert not infos.seen() and infos.match({'left': 100, 'right': 100}) is None
    for stamp in (100, 200, 300, 400):  # keeps the newest 3
        infos.add('left', stamp, f'L{stamp}')
        infos.add('right', stamp + 3, f'R{stamp}')  # within the tolerance
    assert infos.seen() and infos.newest == {'left': 'L400', 'right': 'R400'}
    assert infos.match({'left': 200, 'right': 202}) == {'left': 'L200', 'right': 'R200'}
    assert infos.match({'left': 100, 'right': 100}) is None  # dropped: only 3 kept
    assert infos.match({'left': 500, 'right': 500}) is None
    assert infos.passed({'left': 250, 'right': 250})  # newer ones came: 250's never will
    assert not infos.passed({'left': 500, 'right': 500})
