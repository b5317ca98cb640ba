"""gcp-stereo-bag run on recordings as camera drivers write them: raw, free-running, any names."""

from bag_helpers import cli, crop_msg, PARAMS, read_bag, write_bag
from gcp_stereo_ros.evaluation.datasets import load_frame
from gcp_stereo_ros.ros import messages
from gcp_stereo_ros.ros.params import config_from_params
from gcp_stereo_ros.ros.rosimage import array_to_image_fields, image_to_array
from gcp_stereo_ros.stereo.pipeline import StereoPipeline
from gcp_stereo_ros.tools import bag
from gcp_stereo_ros.tools.bag.files import IMAGE, INFO, stamped_header, TYPES
import numpy as np
import pytest
import yaml


def info_msg(stamp, fields, frame_id):
    return TYPES.CameraInfo(
        header=stamped_header(stamp, frame_id), binning_x=0, binning_y=0,
        roi=TYPES.RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0,
                                   do_rectify=False), **fields)


def raw_recording(path, pair, names=('image_raw',)):
    """Write a bag as a camera driver records it: /cam/<side>/<name>, /cam/<side>/camera_info."""
    topics = {}
    for side in ('left', 'right'):  # camera_info first, as the node would have it
        topics[f'/cam/{side}/camera_info'] = (INFO, [
            (s, info_msg(s, pair.info[side], f'cam_{side}_optical_frame')) for s in (1, 2)])
    for side in ('left', 'right'):
        for name in names:
            fields = array_to_image_fields(pair.raw[side], 'rgb8')
            topics[f'/cam/{side}/{name}'] = (IMAGE, [
                (s, TYPES.Image(header=stamped_header(s, f'cam_{side}_optical_frame'), **fields))
                for s in (1, 2)])
    write_bag(path, topics)
    return path


def test_run_pairs_free_running_cameras_by_the_closest_stamps(tmp_path, capsys):
    """approximate_sync with tolerance 0: the right camera 7 ms late, left image 2 lost."""
    frame, ms = load_frame('motorcycle', 'motorcycle'), 1_000_000
    stamps = {'left': [0, 66 * ms, 99 * ms], 'right': [7 * ms, 40 * ms, 73 * ms, 106 * ms]}
    write_bag(tmp_path / 'in', {f'/{side}/image_rect': (IMAGE, [
        (t, crop_msg(frame, side, t)) for t in stamps[side]]) for side in stamps})
    params = tmp_path / 'approximate.yaml'
    params.write_text(yaml.safe_dump(
        {'/**': {'ros__parameters': {**PARAMS, 'approximate_sync': True}}}))
    assert bag.main(['run', '--in', str(tmp_path / 'in'), '--out', str(tmp_path / 'out'),
                     '--params', str(params)]) == 0
    outputs, _ = read_bag(tmp_path / 'out')
    # the first frame goes: the frame period is known from a side's second image on
    assert [messages.stamp_ns(m.header) for _, m in outputs['/disparity']] == stamps['left'][1:]
    assert 'images without a twin skipped: left 1, right 2' in capsys.readouterr().out
    one = tmp_path / 'one'  # a recording of one frame: the closest stamps
    write_bag(one, {f'/{side}/image_rect': (IMAGE, [(stamps[side][0], crop_msg(
        frame, side, stamps[side][0]))]) for side in stamps})
    assert bag.main(['run', '--in', str(one), '--out', str(tmp_path / 'one_out'),
                     '--params', str(params)]) == 0
    one = read_bag(tmp_path / 'one_out')[0]['/disparity']
    assert [messages.stamp_ns(m.header) for _, m in one] == [0]


def test_run_rectifies_a_raw_recording(tmp_path, distorted_pair):
    """
    Rectifying the recorded raw pair gives back the disparity of the rectified original.

    Measured at this size: 1.7 % of the interior pixels more than 1 px off, mean 0.27 px
    (interpolating twice); the raw pair matched without rectification: 92 %, mean 9.6 px.
    """
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({'/**': {'ros__parameters': {
        'max_disparity': 32, 'use_gcp': False}}}))
    bag_in = raw_recording(tmp_path / 'raw', distorted_pair)
    original = StereoPipeline(config_from_params({'max_disparity': 32, 'use_gcp': False}))(
        distorted_pair.rect['left'], distorted_pair.rect['right']).disparity
    inner = np.zeros(original.shape, bool)
    inner[12:-12, 32 + 12:-12] = True
    off = {}
    for rectify in (True, False):
        out = tmp_path / f'out_{rectify}'
        proc = cli('run', '--in', bag_in, '--out', out, '--params', params,
                   *(['--rectify'] if rectify else []), '--outputs', 'disparity,depth,points2')
        assert proc.returncode == 0, proc.stderr
        assert '/cam/left/image_raw + /cam/right/image_raw' in proc.stdout
        msgs, _ = read_bag(out)
        assert len(msgs['/cam/disparity']) == 2  # outputs under the pair's namespace
        (_, disp_msg), (_, depth_msg), (_, points_msg) = (
            msgs[f'/cam/{t}'][0] for t in ('disparity', 'depth', 'points2'))
        disp = image_to_array(disp_msg.image)
        disp[disp < disp_msg.min_disparity] = np.nan
        valid = inner & np.isfinite(disp) & np.isfinite(original)
        diff = np.abs(disp - original)[valid]
        off[rectify] = (diff > 1).mean(), diff.mean()
        assert disp_msg.header.frame_id == 'cam_left_optical_frame'
        assert (disp_msg.f, disp_msg.t) == (distorted_pair.f, pytest.approx(0.2))
        depth = np.frombuffer(depth_msg.data, '<f4').reshape(167, 247)  # NaN: no depth
        assert depth_msg.encoding == '32FC1'
        positive = np.isfinite(disp) & (disp > 0)
        np.testing.assert_allclose(depth[positive], 330 * 0.2 / disp[positive], rtol=1e-6)
        assert np.isnan(depth[~positive]).all()
        assert (points_msg.height, points_msg.width, points_msg.point_step) == (167, 247, 32)
    assert off[True][0] < 0.05 and off[True][1] < 0.6, off
    assert off[False][0] > 0.5, off  # the comparison can tell


def test_run_finds_the_stereo_pair_or_says_why(tmp_path, distorted_pair, capsys):
    two = raw_recording(tmp_path / 'two', distorted_pair, names=('image_raw', 'image_color'))
    out = tmp_path / 'out'
    assert bag.main(['run', '--in', str(two), '--out', str(out)]) == 1
    err = capsys.readouterr().err
    assert ('more than one stereo pair of image topics' in err
            and '/cam/left/image_color + /cam/right/image_color' in err
            and '/cam/left/image_raw + /cam/right/image_raw' in err and '--left' in err), err
    assert bag.main(['run', '--in', str(two), '--out', str(out), '--left', '/cam/left/image_raw'
                     ]) == 1
    assert '--left and --right go together' in capsys.readouterr().err
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({'/**': {'ros__parameters': {
        'max_disparity': 16, 'use_gcp': False}}}))
    assert bag.main(['run', '--in', str(two), '--out', str(out), '--params', str(params),
                     '--left', '/cam/left/image_color', '--right', '/cam/right/image_color',
                     '--left-info', '/cam/left/camera_info', '--right-info',
                     '/cam/right/camera_info', '--outputs', 'disparity']) == 0
    msgs, _ = read_bag(out)
    assert len(msgs['/cam/disparity']) == 2 and '/cam/gcp_mask' not in msgs
    assert msgs['/cam/disparity'][0][1].t == pytest.approx(0.2)  # camera_info was read


def test_run_pairs_each_image_with_the_camera_info_of_its_stamp(tmp_path, distorted_pair):
    """
    Check a driver's recording that stores each camera_info after its image.

    No pair is lost, none rectified or scaled with another frame's calibration (here the
    second frame's baseline is 0.3 m, the first's 0.2 m).
    """
    topics = {}
    for side in ('left', 'right'):
        fields = array_to_image_fields(distorted_pair.raw[side], 'rgb8')
        frame_id = f'cam_{side}_optical_frame'
        topics[f'/cam/{side}/image_raw'] = (IMAGE, [
            (s * 100, TYPES.Image(header=stamped_header(s, frame_id), **fields))
            for s in (1, 2)])
        infos = []
        for s, baseline in ((1, 0.2), (2, 0.3)):
            info = dict(distorted_pair.info[side])
            if side == 'right':
                p = np.array(info['p'], float)
                p[3] = -distorted_pair.f * baseline
                info['p'] = p
            infos.append((s * 100 + 10, info_msg(s, info, frame_id)))  # recorded after
        topics[f'/cam/{side}/camera_info'] = (INFO, infos)
    write_bag(tmp_path / 'after', topics)
    params = tmp_path / 'params.yaml'
    params.write_text(yaml.safe_dump({'/**': {'ros__parameters': {
        'max_disparity': 32, 'use_gcp': False}}}))
    proc = cli('run', '--in', tmp_path / 'after', '--out', tmp_path / 'out', '--params', params,
               '--rectify', '--outputs', 'disparity')
    assert proc.returncode == 0, proc.stderr
    assert 'camera_info' not in proc.stderr, proc.stderr
    msgs, _ = read_bag(tmp_path / 'out')
    got = [(messages.stamp_ns(m.header), m.t) for _, m in msgs['/cam/disparity']]
    assert got == [(1, pytest.approx(0.2)), (2, pytest.approx(0.3))]
