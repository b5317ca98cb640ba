"""
gcp-stereo-bag: rosbag2 tools for gcp_stereo_node, no ROS install needed (rosbags, rclpy).

  make  stereo pairs of a dataset -> a bag with the node's input topics and the ground truth
  run   bag in -> bag out with the node's outputs, computed offline exactly as the node does
  play  a bag into a live ROS graph at its recorded timing, like `ros2 bag play`

Bags written by `make` (every topic under --namespace; all messages of a frame carry the
frame's stamp as header stamp and as bag timestamp, the ground truth written first):
  left/image_rect, right/image_rect    sensor_msgs/Image, rgb8 or mono8 as the dataset stores
                                       it; frame_id left_camera, right_camera (with
                                       --compressed: left/image_rect/compressed, ...,
                                       sensor_msgs/CompressedImage, png or jpeg)
  left/camera_info, right/camera_info  sensor_msgs/CameraInfo; when the dataset knows them, f in
                                       K and P, P_right[3] = -f * baseline and the principal
                                       points (KITTI calib files, MiddEval3/ETH3D calib.txt,
                                       Motorcycle; else the image centre), else K = P = 0
                                       (uncalibrated)
  gt/disparity                         sensor_msgs/Image 32FC1, left disparity in px, 0 = unknown
  gt/valid                             sensor_msgs/Image mono8, 255 = pixel scored (ground truth
                                       known and inside the dataset's mask, e.g. non-occluded)
  gt/frame_name                        std_msgs/String, the dataset's frame name
Images and camera_info are recorded with the sensor-data QoS (best effort, volatile, keep
last 5) the node subscribes with; the ground truth with the default QoS (reliable).

`run` reads any recording with one stereo pair of image topics (sensor_msgs/Image or
CompressedImage, rectified, or raw with --rectify): --left and --right name them, else the
pair is found (two image topics whose names differ only in left/right), and so are their
camera_info topics (beside the image topics; --left-info, --right-info). It pairs images by
stamp (the node's sync parameters: exact by default) and scores a pair against the gt/
messages whose bag timestamp is the pair's stamp. Its output bag holds every input message
(earlier outputs excepted) plus the --outputs (default disparity, gcp_mask, confidence; also
depth, points2), built as the node builds them, under the stereo namespace (--namespace, or
the part of the image topics before left/right), stamped with the left header and written
at the bag timestamp of the image that completed the pair. A pair the node would skip
(a bad image, a pair over memory_limit_mb) is skipped with a line on stderr. Bags are
written to a hidden sibling and renamed into place on success; Ctrl-C or SIGTERM removes
it, and one left by a killed run is removed by the next run on the same output. With --png,
each pair's colour-mapped disparity (a colour bar under it: the scale in px, far to near)
and GCP mask are written as PNGs too.

The modules: `files` (types, topics, reading and writing bags), `make`, `topics` (which
topics `run` reads), `run`, `play`; `python -m gcp_stereo_ros.tools.bag` is this script.
"""
import argparse
from pathlib import Path

from rosbags.rosbag2.errors import WriterError
from rosbags.typesys import TypesysError

from . import make, play, run
from .files import FRAME_RATE_HZ, OUTPUTS, PROG
from ..cli import console_main, positive


def _outputs(text):
    names = {n.strip() for n in text.split(',') if n.strip()}
    unknown = names - set(OUTPUTS)
    if unknown or not names:
        raise argparse.ArgumentTypeError(f'unknown output(s) {", ".join(sorted(unknown))}; '
                                         f'choose from {",".join(OUTPUTS)}')
    return names


STORAGE = {'choices': ('sqlite3', 'mcap'), 'default': 'mcap',
           'help': 'storage plugin of the output bag (default mcap)'}


def add_run_options(ap):
    """Add the options of `run` that apply to any bag (all but --in, --out, --force) to `ap`."""
    ap.add_argument('--params', type=Path, metavar='YAML',
                    help='node parameters file, e.g. config/gcp_stereo.yaml, or what `ros2 '
                         'param dump` wrote (default: the node defaults)')
    ap.add_argument('--left', metavar='TOPIC',
                    help='left image topic, sensor_msgs/Image or CompressedImage (default: '
                         'the one stereo pair of image topics in the bag)')
    ap.add_argument('--right', metavar='TOPIC', help='right image topic (with --left)')
    ap.add_argument('--left-info', metavar='TOPIC',
                    help='left camera_info topic (default: camera_info beside the left images, '
                         'if the bag has it)')
    ap.add_argument('--right-info', metavar='TOPIC', help='right camera_info topic')
    ap.add_argument('--rectify', action='store_true',
                    help='the images are raw: rectify them with the camera_info K, D, R, P '
                         "(default: the params file's rectify, else false)")
    ap.add_argument('--outputs', type=_outputs, default={'disparity', 'gcp_mask', 'confidence'},
                    metavar='LIST',
                    help=f'comma-separated outputs to write, of {",".join(OUTPUTS)} (default '
                         'disparity,gcp_mask,confidence; depth and points2 need camera_info)')
    ap.add_argument('--png', type=Path, metavar='DIR',
                    help='write colour-mapped disparity PNGs (with a colour bar in px) and '
                         'GCP-mask PNGs here')
    ap.add_argument('--storage', **STORAGE)
    ap.add_argument('--namespace', default='', metavar='NS',
                    help='look for the stereo pair under this namespace and write the outputs '
                         'there (default: the namespace of the image topics)')


def parser():
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest='command', required=True)
    force = {'action': 'store_true', 'help': 'replace an existing --out'}

    mk = sub.add_parser('make', help='dataset stereo pairs -> bag with the node input topics '
                                     'and ground truth')
    mk.add_argument('--dataset', required=True, metavar='PATH',
                    help='dataset folder in any supported layout (searched recursively), or '
                         "'motorcycle'")
    mk.add_argument('--frames', nargs='+', metavar='NAME',
                    help='frame names (default: all of the dataset)')
    mk.add_argument('--storage', **STORAGE)
    mk.add_argument('--out', required=True, type=Path, metavar='BAG',
                    help='bag to write (a directory)')
    mk.add_argument('--rate', type=positive, default=FRAME_RATE_HZ, metavar='HZ',
                    help=f'frames per second (default {FRAME_RATE_HZ:g})')
    mk.add_argument('--namespace', default='', metavar='NS',
                    help='topics under this namespace (default: none, e.g. /left/image_rect)')
    mk.add_argument('--compressed', choices=('png', 'jpeg'),
                    help='write sensor_msgs/CompressedImage on left/image_rect/compressed, '
                         'right/image_rect/compressed, as image_transport does (png is '
                         'lossless; jpeg quality 95)')
    mk.add_argument('--force', **force)

    rn = sub.add_parser('run', help='bag in -> bag out with disparity, gcp_mask, confidence, '
                                    'depth, points2, as the node')
    rn.add_argument('--in', dest='inp', required=True, type=Path, metavar='BAG',
                    help='bag directory, or its .mcap / .db3 file')
    rn.add_argument('--out', required=True, type=Path, metavar='BAG',
                    help='bag to write: the input plus the outputs')
    add_run_options(rn)
    rn.add_argument('--force', **force)

    pl = sub.add_parser('play',
                        help='publish a bag into the live ROS graph at its recorded timing')
    pl.add_argument('--in', dest='inp', required=True, type=Path, metavar='BAG',
                    help='bag directory, or its .mcap / .db3 file')
    pl.add_argument('--rate', type=positive, default=1.0, metavar='R',
                    help='speed factor (default 1)')
    pl.add_argument('--loop', action='store_true',
                    help='play again and again, with the recorded stamps (as ros2 bag play '
                         '--loop), each pass one frame period after the last (the median '
                         f'step between stamps; {1 / FRAME_RATE_HZ:g} s for a bag of one stamp)')
    pl.add_argument('--wait-subscribers', type=float, default=5.0, metavar='SECONDS',
                    help='wait up to this long for a subscriber on every image topic '
                         '(ground truth excepted) before publishing (default 5)')
    return ap


@console_main(PROG, errors=(WriterError, TypesysError))
def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    try:
        {'make': make, 'run': run, 'play': play}[args.command].command(args)
    except BaseException as err:
        if args.command != 'play':
            err.add_note(f'{args.out} not written')
        raise
