"""
gcp-stereo-load: feed the node a camera-rate stream and report whether it keeps up.

Starts `gcp_stereo_node` as its own process in a private ROS graph, publishes one real pair
back to back (left, then right) at `--rate` Hz for `--seconds`, and reports pairs sent and
processed (the rest were dropped as stale), latency from publishing to receiving the
disparity (median, max), and the node's RSS over the run (it should stay flat).
"""
import argparse
import json
from pathlib import Path
import statistics
import sys
import threading
import time

from .cli import console_main, positive
from ..evaluation.datasets import list_frames, load_frame
from ..ros.graph import peer_graph
from ..ros.messages import stamp_ns
from ..ros.rosimage import array_to_image_fields


def rss_mb(pid):
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            return int(line.split()[1]) / 1024.0
    return float('nan')


def node_param(text):
    """Argparse type: `NAME:=VALUE` -> (NAME, VALUE)."""
    name, sep, value = text.partition(':=')
    if not (name and sep):
        raise argparse.ArgumentTypeError(f'expected NAME:=VALUE, got {text!r}')
    return name, value


@console_main('gcp-stereo-load')
def main(argv=None):
    ap = argparse.ArgumentParser(prog='gcp-stereo-load', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--dataset', default='motorcycle')
    ap.add_argument('--frame', help='frame name (default: the first)')
    ap.add_argument('--rate', type=positive, default=30.0)
    ap.add_argument('--seconds', type=positive, default=60.0)
    ap.add_argument('-p', '--param', action='append', default=[], type=node_param,
                    metavar='NAME:=VALUE',
                    help='node parameter, as with --ros-args -p; repeatable')
    ap.add_argument('--json', type=Path)
    args = ap.parse_args(argv)

    frame = load_frame(args.dataset, args.frame or list_frames(args.dataset)[0])
    params = {'max_disparity': frame.max_disp, **dict(args.param)}
    with peer_graph('gcp_stereo_load', params) as (peer, node):
        report = _measure(args, frame, peer, node)
    for key, value in report.items():
        print(f'{key:<18} {value}')
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


def _measure(args, frame, peer, node):
    """Warm up, then publish at args.rate for args.seconds; the report (see the module doc)."""
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image
    from stereo_msgs.msg import DisparityImage

    pubs = [peer.create_publisher(Image, f'{s}/image_rect', qos_profile_sensor_data)
            for s in ('left', 'right')]
    msgs = []
    for image in (frame.left, frame.right):
        fields = array_to_image_fields(image, 'rgb8' if image.ndim == 3 else 'mono8')
        msgs.append(Image(**{**fields, 'data': fields['data'].tobytes()}))
    sent, latency = {}, []
    lock = threading.Lock()

    def on_disparity(msg):
        stamp = stamp_ns(msg.header)
        with lock:
            if stamp in sent:
                latency.append(time.monotonic() - sent[stamp])

    peer.create_subscription(DisparityImage, 'disparity', on_disparity, 10)

    def publish(stamp_ns):
        for pub, m in zip(pubs, msgs):
            m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
            m.header.frame_id = 'left'
            with lock:
                sent[stamp_ns] = time.monotonic()
            pub.publish(m)

    # Warm up (subscription matching, Numba and torch first calls) before measuring.
    deadline = time.monotonic() + 120
    while not latency and time.monotonic() < deadline and node.poll() is None:
        publish(time.time_ns())
        time.sleep(1.0)
    if node.poll() is not None:
        raise ChildProcessError(f'the node exited with status {node.returncode}')
    if not latency:
        raise TimeoutError('the node produced no disparity within 120 s')
    with lock:
        sent.clear()
        latency.clear()
    rss = [rss_mb(node.pid)]
    start = time.monotonic()
    n = 0
    while time.monotonic() - start < args.seconds:
        publish(time.time_ns())
        n += 1
        if n % max(1, int(args.rate * 10)) == 0:
            rss.append(rss_mb(node.pid))
        time.sleep(max(0.0, start + n / args.rate - time.monotonic()))
    time.sleep(3.0)  # let the last frame through
    rss.append(rss_mb(node.pid))
    return {
        'frame': frame.name, 'size': list(frame.left.shape[:2][::-1]), 'rate_hz': args.rate,
        'seconds': args.seconds, 'pairs_sent': n, 'pairs_processed': len(latency),
        'pairs_dropped': n - len(latency), 'latency_median_s': statistics.median(latency),
        'latency_max_s': max(latency), 'rss_mb': [round(r, 1) for r in rss],
    }


if __name__ == '__main__':
    sys.exit(main())
