"""PairSync: exact and approximate stereo pairing, drops, the unmatched streak; CameraInfos."""
from gcp_stereo_ros.ros.params import make_sync
from gcp_stereo_ros.ros.sync import CameraInfos, PairSync
import pytest

MS = 1_000_000  # nanoseconds


def test_exact_pairs_identical_stamps_in_either_order():
    sync = PairSync()
    assert sync.add('left', 100, 'L100') is None
    assert sync.add('right', 100, 'R100') == (100, 'L100', 'R100')
    assert sync.add('right', 200, 'R200') is None
    assert sync.add('left', 200, 'L200') == (200, 'L200', 'R200')
    assert (sync.pairs, sync.dropped_left, sync.dropped_right) == (2, 0, 0)


def test_exact_drops_and_counts_unmatched_stamps():
    sync = PairSync()
    assert sync.add('left', 100, 'L100') is None
    assert sync.add('right', 101, 'R101') is None  # 1 ns apart: not exact
    assert sync.add('left', 200, 'L200') is None
    assert sync.add('right', 200, 'R200') == (200, 'L200', 'R200')
    assert (sync.pairs, sync.dropped_left, sync.dropped_right) == (1, 1, 1)
    # Older than the emitted pair, from one side only: a straggler, dropped at the next pair.
    assert sync.add('left', 101, 'L101') is None
    assert sync.add('left', 300, 'L300') is None
    assert sync.add('right', 300, 'R300') == (300, 'L300', 'R300')
    assert (sync.pairs, sync.dropped_left, sync.dropped_right) == (2, 2, 1)


def test_exact_out_of_order_arrival():
    sync = PairSync()
    assert sync.add('left', 300, 'L300') is None
    assert sync.add('left', 100, 'L100') is None
    assert sync.add('right', 200, 'R200') is None
    assert sync.add('right', 100, 'R100') == (100, 'L100', 'R100')
    assert sync.add('left', 200, 'L200') == (200, 'L200', 'R200')
    assert sync.add('right', 300, 'R300') == (300, 'L300', 'R300')
    assert (sync.pairs, sync.dropped_left, sync.dropped_right) == (3, 0, 0)


def test_exact_queue_overflow_drops_oldest_stamp():
    sync = PairSync(queue_size=3)
    for stamp in (400, 100, 300, 200):  # 4 > 3: stamp 100 goes although it came second
        assert sync.add('left', stamp, f'L{stamp}') is None
    assert sync.dropped_left == 1
    assert sync.add('right', 100, 'R100') is None
    assert sync.add('right', 200, 'R200') == (200, 'L200', 'R200')
    # R100 discarded by the pair
    assert (sync.pairs, sync.dropped_left, sync.dropped_right) == (1, 1, 1)


def test_pair_discards_everything_older_on_both_sides():
    sync = PairSync()
    for stamp in (100, 200, 400):
        sync.add('left', stamp, f'L{stamp}')
    for stamp in (150, 250):
        sync.add('right', stamp, f'R{stamp}')
    assert sync.add('right', 400, 'R400') == (400, 'L400', 'R400')
    assert (sync.dropped_left, sync.dropped_right) == (2, 2)
    assert sync.add('left', 250, 'L250') is None  # R250 was discarded
    assert sync.add('left', 500, 'L500') is None
    assert sync.add('right', 500, 'R500') == (500, 'L500', 'R500')
    assert sync.dropped_left == 3  # L250, a straggler, at this pair


def test_exact_ignores_tolerance():
    sync = PairSync(approximate=False, tolerance=1.0)
    sync.add('left', 100, 'L')
    assert sync.add('right', 101, 'R') is None


def test_approximate_pairs_within_tolerance_only():
    sync = PairSync(approximate=True, tolerance=0.005)
    assert sync.add('left', 1000 * MS, 'L1') is None
    # exactly at the tolerance
    assert sync.add('right', 1005 * MS, 'R1') == (1000 * MS, 'L1', 'R1')
    assert sync.add('left', 2000 * MS, 'L2') is None
    assert sync.add('right', 2005 * MS + 1, 'R2') is None  # 1 ns beyond it
    assert sync.add('right', 1997 * MS, 'R3') == (2000 * MS, 'L2', 'R3')
    # R2 is newer: still queued
    assert (sync.pairs, sync.dropped_left, sync.dropped_right) == (2, 0, 0)


def test_approximate_chooses_closest_match():
    sync = PairSync(approximate=True, tolerance=0.010)
    sync.add('left', 100 * MS, 'L100')
    sync.add('left', 106 * MS, 'L106')
    sync.add('left', 111 * MS, 'L111')
    assert sync.add('right', 108 * MS, 'R108') == (106 * MS, 'L106', 'R108')
    assert sync.dropped_left == 1  # L100; L111 may still pair
    assert sync.add('right', 112 * MS, 'R112') == (111 * MS, 'L111', 'R112')


def test_approximate_tie_keeps_the_newer_candidate():
    sync = PairSync(approximate=True, tolerance=0.010)
    sync.add('left', 100 * MS, 'L100')
    sync.add('left', 106 * MS, 'L106')
    assert sync.add('right', 103 * MS, 'R103') == (100 * MS, 'L100', 'R103')
    assert sync.add('right', 107 * MS, 'R107') == (106 * MS, 'L106', 'R107')
    assert sync.dropped_left == 0


def test_approximate_out_of_order_arrival():
    sync = PairSync(approximate=True, tolerance=0.002)
    assert sync.add('right', 301 * MS, 'R301') is None
    assert sync.add('right', 101 * MS, 'R101') is None
    assert sync.add('left', 200 * MS, 'L200') is None
    assert sync.add('left', 100 * MS, 'L100') == (100 * MS, 'L100', 'R101')
    assert sync.add('left', 300 * MS, 'L300') == (300 * MS, 'L300', 'R301')
    # L200 never got a twin
    assert (sync.pairs, sync.dropped_left, sync.dropped_right) == (2, 1, 0)


def test_unmatched_streak_grows_while_one_side_is_missing():
    sync = PairSync(queue_size=2)
    for i in range(6):  # the right images of 6 frames are lost
        sync.add('left', i, f'L{i}')
    assert sync.unmatched_streak('left') == 4
    assert sync.unmatched_streak('right') == 0
    sync.add('right', 3, 'R3')  # older than queued L4, L5: kept
    assert sync.unmatched_streak('right') == 0
    assert sync.add('right', 5, 'R5') == (5, 'L5', 'R5')
    assert (sync.dropped_left, sync.dropped_right) == (5, 1)
    assert sync.unmatched_streak('left') == sync.unmatched_streak('right') == 0
    sync.add('right', 4, 'R4')  # older than the pair: dropped at the next one
    sync.add('left', 6, 'L6')
    assert sync.add('right', 6, 'R6') == (6, 'L6', 'R6')
    assert sync.dropped_right == 2 and sync.unmatched_streak('right') == 0


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
        PairSync(**kwargs)


def test_rejects_unknown_side():
    sync = PairSync()
    with pytest.raises(ValueError, match="'left' or 'right'.*'center'"):
        sync.add('center', 0, None)
    with pytest.raises(ValueError, match="'left' or 'right'"):
        sync.unmatched_streak('Left')


def test_stream_restart_starts_pairing_afresh():
    sync = PairSync()
    assert sync.add('left', 50_000_000_000, 'l1') is None
    assert sync.add('right', 50_000_000_000, 'r1') == (50_000_000_000, 'l1', 'r1')
    assert sync.add('left', 49_900_000_000, 'late') is None  # one side back: a straggler
    assert sync.add('left', 1_000_000_000, 'l2') is None  # it replaces the straggler
    assert sync.dropped_left == 1
    assert sync.add('right', 1_000_000_000, 'r2') == (1_000_000_000, 'l2', 'r2')  # both back


@pytest.mark.parametrize('approximate', [False, True])
def test_looped_one_frame_bag_pairs_on_every_pass(approximate):
    """A one-frame bag played with --loop repeats one stamp: every pass is a pair."""
    sync = PairSync(approximate=approximate, tolerance=0.01)
    for n in range(1, 6):
        assert sync.add('left', 7 * MS, f'L{n}') is None
        assert sync.add('right', 7 * MS, f'R{n}') == (7 * MS, f'L{n}', f'R{n}')
    assert (sync.pairs, sync.dropped_left, sync.dropped_right) == (5, 0, 0)


def test_looped_short_bag_pairs_every_frame_of_every_pass():
    """Three frames 0.1 s apart, looped: each pass starts 0.2 s before the last pair."""
    sync = PairSync()
    got = []
    for _ in range(4):
        for stamp in (0, 100 * MS, 200 * MS):
            for side in ('left', 'right'):
                pair = sync.add(side, stamp, side)
                if pair is not None:
                    got.append(pair[0])
    assert got == [0, 100 * MS, 200 * MS] * 4
    assert (sync.dropped_left, sync.dropped_right) == (0, 0)


def test_queues_are_bounded_in_bytes_too():
    sync = PairSync(queue_size=100, max_bytes=250)
    for i in range(5):
        assert sync.add('left', i, f'L{i}', 100) is None
    assert sync.dropped_left == 3  # two 100-byte images fit in 250 bytes
    assert sync.add('right', 4, 'R4', 100) == (4, 'L4', 'R4')
    assert sync.add('right', 9, 'big', 1000) is None  # the newest is kept, whatever its size
    assert sync.add('left', 9, 'L9', 100) == (9, 'L9', 'big')


def test_node_queues_hold_a_quarter_of_the_memory_limit():
    assert make_sync({'queue_size': 1000, 'memory_limit_mb': 3072}).max_bytes == 768 << 20


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
