"""gcp-stereo-bag refusing what it cannot use: bad bags, bad pairs and parameters, signals."""
import os
import shutil
import signal
import subprocess
import sys
import time

from bag_helpers import (cli, crop_msg, image_msg, PARAMS, read_bag, REPO, string_msg, TYPESTORE,
                         write_bag)
from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.ros import messages
from gcp_stereo_ros.tools import bag
from gcp_stereo_ros.tools.bag import make as bag_make
from gcp_stereo_ros.tools.bag.files import IMAGE, PROG, STRING
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
import yaml


def bad_bags(tmp_path):
    """{case: path} of inputs `run` must refuse."""
    bags = {}
    for storage in ('sqlite3', 'mcap'):
        good = tmp_path / f'good_{storage}'
        assert bag.main(['make', '--dataset', 'motorcycle', '--storage', storage,
                         '--out', str(good)]) == 0
        cut = bags[f'truncated {storage}'] = tmp_path / f'truncated_{storage}'
        shutil.copytree(good, cut)
        data, = (p for p in cut.iterdir() if p.suffix in ('.db3', '.mcap'))
        data.write_bytes(data.read_bytes()[:data.stat().st_size // 2])
    bags['text file'] = tmp_path / 'notes.txt'
    bags['text file'].write_text('not a bag\n')
    bags['text file named .db3'] = tmp_path / 'notes.db3'
    bags['text file named .db3'].write_text('not a bag\n')
    bags['no image topics'] = tmp_path / 'chatter'
    write_bag(bags['no image topics'], {'/chatter': (STRING, [(1, string_msg('hello'))])})
    bags['wrong image type'] = tmp_path / 'strings'
    write_bag(bags['wrong image type'], {
        '/left/image_rect': (STRING, [(1, string_msg('left'))]),
        '/right/image_rect': (STRING, [(1, string_msg('right'))])})
    bags['only bad pairs'] = tmp_path / 'only_bad'
    write_bag(bags['only bad pairs'], {
        f'/{side}/image_rect': (
            IMAGE, [(1, image_msg(1, 'yuv422')), (2, image_msg(2, 'yuv422'))])
        for side in ('left', 'right')})
    return bags


REASONS = {
    'truncated sqlite3': 'malformed', 'truncated mcap': 'not a readable rosbag2',
    'text file': 'not a readable rosbag2', 'text file named .db3': 'not a database',
    'no image topics': 'no stereo pair of image topics (topics: /chatter (String))',
    'wrong image type': 'no stereo pair of image topics (topics: /left/image_rect (String), '
                        '/right/image_rect (String))',
    'only bad pairs': 'none of its 2 pairs could be processed',
}


def test_bad_input_bags_are_refused_without_output(tmp_path, params_file, capsys):
    bags = bad_bags(tmp_path)
    capsys.readouterr()
    for case, path in bags.items():
        out = tmp_path / f'out_{path.name}'
        assert bag.main(['run', '--in', str(path), '--out', str(out),
                         '--params', str(params_file)]) != 0, case
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert err.startswith('gcp-stereo-bag: error: ') and REASONS[case] in err, (case, err)
        assert err.endswith(f'{out} not written'), err
        assert not out.exists(), case
    assert [p.name for p in tmp_path.iterdir() if 'partial' in p.name] == []
    # the real command line: exit status 1, one line on stderr, no traceback
    proc = cli('run', '--in', bags['truncated mcap'], '--out', tmp_path / 'cli_out')
    assert proc.returncode == 1 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert 'Traceback' not in proc.stderr and not (tmp_path / 'cli_out').exists()


def test_run_skips_a_bad_pair_as_the_node_does(tmp_path, params_file, capsys):
    frame = load_frame('motorcycle', 'motorcycle')
    path = tmp_path / 'in'
    write_bag(path, {f'/{side}/image_rect': (IMAGE, [
        (1, crop_msg(frame, side, 1)),
        (2, crop_msg(frame, side, 2, 'yuv422' if side == 'left' else 'rgb8')),
        (3, crop_msg(frame, side, 3, rows=120 if side == 'left' else 100)),
        (4, crop_msg(frame, side, 4))]) for side in ('left', 'right')})
    assert bag.main(['run', '--in', str(path), '--out', str(tmp_path / 'out'),
                     '--params', str(params_file)]) == 0
    out = capsys.readouterr()
    assert [line for line in out.err.splitlines() if line.startswith(PROG)] == [
        'gcp-stereo-bag: skipping pair at stamp 2 ns: /left/image_rect: unsupported '
        "encoding 'yuv422'; expected one of mono8, mono16, 32FC1, rgb8, bgr8, rgba8, bgra8",
        'gcp-stereo-bag: skipping pair at stamp 3 ns: left image is 160x120 but right '
        'image is 160x100 (width x height); a rectified pair has one size']
    assert ' processed (confidence, disparity, gcp_mask written), 2 skipped;' in out.out
    outputs, _ = read_bag(tmp_path / 'out')
    assert [messages.stamp_ns(m.header) for _, m in outputs['/disparity']] == [1, 4]
    too_high = tmp_path / 'theta.yaml'  # the shipped weights' confidence is at most 0.961
    too_high.write_text(yaml.safe_dump(
        {'/**': {'ros__parameters': {**PARAMS, 'census.theta': 0.97}}}))
    assert bag.main(['run', '--in', str(path), '--out', str(tmp_path / 'out'), '--force',
                     '--params', str(too_high)]) == 0
    assert ('gcp-stereo-bag: warning: theta 0.97 selects no GCP: the CNN confidence is at most'
            in capsys.readouterr().err)


def slow_bag(path, pairs):
    """Write a bag of `pairs` Motorcycle frames: seconds of work for `run`."""
    frame = load_frame('motorcycle', 'motorcycle')
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {name: writer.add_connection(f'/{name}', msgtype, typestore=TYPESTORE)
                 for name, (msgtype, _) in bag_make.input_topics().items()}
        for i in range(pairs):
            stamp = (i + 1) * 100_000_000
            for name, msg in bag_make.frame_messages(frame, stamp).items():
                if name in conns:
                    writer.write(conns[name], stamp,
                                 TYPESTORE.serialize_cdr(msg, conns[name].msgtype))


def test_staging_is_removed_on_sigterm_and_after_sigkill(tmp_path):
    slow_bag(tmp_path / 'in', 20)
    out = tmp_path / 'out'
    for sig in (signal.SIGTERM, signal.SIGKILL):
        proc = subprocess.Popen([sys.executable, '-m', 'gcp_stereo_ros.tools.bag', 'run',
                                 '--in', str(tmp_path / 'in'), '--out', str(out)],
                                cwd=REPO, env=os.environ, stderr=subprocess.PIPE, text=True)
        staging = tmp_path / f'.out.partial-{proc.pid}'
        end = time.monotonic() + 60
        while not staging.exists():
            assert time.monotonic() < end and proc.poll() is None, 'no staging folder'
            time.sleep(0.05)
        time.sleep(1.0)  # in the middle of the run
        proc.send_signal(sig)
        err = proc.communicate(timeout=30)[1]
        if sig == signal.SIGTERM:
            assert proc.returncode == 128 + signal.SIGTERM, err
            assert err.strip().splitlines()[-1] == (
                f'gcp-stereo-bag: terminated; {out} not written')
            assert not staging.exists()
        else:
            assert staging.exists()  # nothing runs on SIGKILL ...
    assert not out.exists()
    assert bag.main(['make', '--dataset', 'motorcycle', '--out', str(out)]) == 0
    assert not staging.exists()  # ... the next run on the same output removes it
    assert sorted(p.name for p in tmp_path.iterdir()) == ['in', 'out']


def test_existing_output_needs_force(tmp_path, capsys):
    out = tmp_path / 'bag'
    out.mkdir()
    (out / 'keep').write_text('mine')
    make = ['make', '--dataset', 'motorcycle', '--out', str(out)]
    assert bag.main(make) == 1
    assert 'exists; pass --force' in capsys.readouterr().err
    assert (out / 'keep').read_text() == 'mine'
    assert bag.main(make + ['--force']) == 0
    assert not (out / 'keep').exists()
    assert read_bag(out)[0]['/gt/frame_name'][0][1].data == 'motorcycle'


@pytest.mark.parametrize('values, reason', [
    ({'max_disparity': 2000}, 'max_disparity must be in [1, 1024], got 2000'),
    ({'census.window': 8}, 'census.window must be in [3, 11] in steps of 2 from 3, got 8'),
    ({'sad.P1': 30.0}, 'sad: P2 (0.5) must be >= P1 (30.0)'),
])
def test_run_refuses_bad_parameters_naming_the_file(tmp_path, capsys, values, reason):
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({'/**': {'ros__parameters': values}}))
    out = tmp_path / 'out'
    assert bag.main(['run', '--in', str(tmp_path / 'no_bag'), '--out', str(out),
                     '--params', str(params)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f'gcp-stereo-bag: error: {params}: {reason}' + (
        ': a disparity jump may not cost less than a 1 px step' if 'P2' in reason else '') + (
        f'; {out} not written')
    assert not out.exists()
