"""
`make demo`: the whole ROS pipeline on the bundled default data.

Builds a rosbag per frame (Middlebury 2014 Motorcycle from scikit-image, and KITTI 2012
000070 when ../shared/data is beside the checkout), starts gcp_stereo_node in a private ROS
graph, plays each bag into it with `gcp-stereo-bag play`, records `disparity` and
`gcp_mask`, writes colour-mapped PNGs to --out (each disparity with a colour bar: its
scale in px, far to near), prints the error rates against the ground truth and stops
everything. --readme-image writes the Motorcycle disparity once more, README_WIDTH px
across: doc/images/motorcycle_disparity.png is

    gcp-stereo-demo --out out --readme-image doc/images/motorcycle_disparity.png
"""
import argparse
import os
from pathlib import Path
import shutil
import subprocess
import sys
import time

import numpy as np

from .cli import console_main
from ..evaluation.datasets import load_frame
from ..evaluation.metrics import error_rates
from ..evaluation.viz import disparity_picture, save_png
from ..ros.graph import package_file, peer_graph
from ..ros.rosimage import image_to_array
from ..stereo.images import mask_image

SHARED = Path(__file__).resolve().parents[3] / 'shared' / 'data'
README_WIDTH = 480  # px across of the --readme-image picture (the pair is 741 x 497)


def frames_to_show():
    """(dataset, frame name) pairs: Motorcycle, and KITTI 000070 when the shared data is here."""
    frames = [('motorcycle', 'motorcycle')]
    if (SHARED / 'kitti2012').is_dir():
        frames.append((str(SHARED), 'kitti2012/000070_10'))
    return frames


def run(cmd):
    """Run `python -m <cmd>`; a failure (reported by the child itself) raises."""
    status = subprocess.run([sys.executable, '-m', *cmd], env=os.environ).returncode
    if status:
        raise ChildProcessError(f'{" ".join(cmd[:2])} exited with status {status}')


@console_main('gcp-stereo-demo')
def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog='gcp-stereo-demo', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--out', type=Path, default=Path('out'),
                    help='folder of the PNGs and the bags (default out)')
    ap.add_argument('--readme-image', type=Path, metavar='PNG',
                    help=f'also write the Motorcycle disparity, {README_WIDTH} px across with '
                         'its colour bar, here (the picture the README shows)')
    args = ap.parse_args(argv)
    frames = frames_to_show()
    args.out.mkdir(parents=True, exist_ok=True)
    bags = args.out / 'bags'
    shutil.rmtree(bags, ignore_errors=True)
    for i, (dataset, name) in enumerate(frames):
        run(['gcp_stereo_ros.tools.bag', 'make', '--dataset', dataset, '--frames', name,
             '--storage', 'mcap', '--out', str(bags / f'frame{i}')])

    rows = []
    with peer_graph('gcp_stereo_demo',
                    params_file=package_file('config/gcp_stereo.yaml')) as (peer, node):
        from sensor_msgs.msg import Image
        from stereo_msgs.msg import DisparityImage

        got: dict[str, list] = {'disparity': [], 'gcp_mask': []}
        peer.create_subscription(DisparityImage, 'disparity', got['disparity'].append, 10)
        peer.create_subscription(Image, 'gcp_mask', got['gcp_mask'].append, 10)
        for i, (dataset, name) in enumerate(frames):
            run(['gcp_stereo_ros.tools.bag', 'play', '--in', str(bags / f'frame{i}'),
                 '--wait-subscribers', '60'])
            deadline = time.monotonic() + 120
            while min(len(v) for v in got.values()) <= i:
                if time.monotonic() > deadline or node.poll() is not None:
                    raise TimeoutError(f'no disparity from the node for {name}')
                time.sleep(0.05)
            frame = load_frame(dataset, name)
            disp_msg = got['disparity'][i]
            disp = image_to_array(disp_msg.image)
            disp[disp < disp_msg.min_disparity] = np.nan
            # The message holds d - (cx_left - cx_right) (min_disparity is d = 0): back to d.
            disp -= disp_msg.min_disparity
            gcp = image_to_array(got['gcp_mask'][i]) > 0
            stem = name.replace('/', '_')
            top = disp_msg.max_disparity - disp_msg.min_disparity + 1
            save_png(args.out / f'{stem}_disparity.png', disparity_picture(disp, top))
            if args.readme_image and name == 'motorcycle':
                save_png(args.readme_image, disparity_picture(disp, top, README_WIDTH))
            save_png(args.out / f'{stem}_gcp_mask.png', mask_image(gcp))
            assert frame.gt is not None  # the demo's frames have ground truth
            rows.append((name, error_rates(disp, frame.gt, frame.valid), 100 * gcp.mean()))
    keys = ('bad1', 'bad2', 'bad3', 'bad5', 'mae', 'density', 'bad3_published')
    print(f'\n{"frame":<22}' + ''.join(f'{k.replace("_published", "pub"):>9}' for k in keys)
          + f'{"GCPs %":>8}')
    for name, r, density in rows:
        print(f'{name:<22}' + ''.join(f'{r[k]:9.2f}' for k in keys) + f'{density:8.1f}')
    print('(badN: % of ground-truth pixels with error > N px, unpublished ones filled as the '
          'KITTI devkit does; density: % published; bad3pub: % of the published off by more '
          'than 3 px; mae in px)')
    print(f'PNGs in {args.out}/; node exited with {node.returncode}')


if __name__ == '__main__':
    sys.exit(main())
