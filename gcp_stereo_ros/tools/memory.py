"""
gcp-stereo-memory: the node's memory through a sequence of image sizes and disparity ranges.

Starts `gcp_stereo_node` as its own process in a private ROS graph. A step WxH:D sets
max_disparity to D, publishes one real pair resized to WxH and waits for its disparity or
the node's refusal; `idle` waits 3 s (the node lets its arrays go after 2 s without input).
After each step it prints the node's RSS and its peak during the step (/proc/<pid>/status;
the peak is reset through /proc/<pid>/clear_refs, Linux only) beside the pipeline's own
estimate for the pair (`memory_bytes`), which the node compares with memory_limit_mb.

With --pipeline it measures a StereoPipeline in this process instead, without ROS: for each
step the peak RSS of a second pair of that size above the process without kept arrays, as
a stream of such pairs needs it, against the estimate.
"""
import argparse
from pathlib import Path
import time

import cv2
import yaml

from .bag import wait_for_subscribers
from .load import rss_mb
from ..evaluation.datasets import list_frames, load_frame
from ..ros.graph import peer_graph
from ..ros.messages import stamp_ns
from ..ros.params import config_from_params
from ..ros.rosimage import array_to_image_fields
from ..stereo.pipeline import memory_bytes, MIB, mmap_large_arrays, StereoPipeline

STEPS = ['640x480:128', 'idle', '3840x2160:1024', '1920x1080:1024', '3840x2160:64',
         '1920x1080:256', 'idle', '1920x1080:128', '640x480:128', 'idle']
IDLE_SECONDS = 3.0
TIMEOUT_SECONDS = 600.0


def main(argv=None):
    ap = argparse.ArgumentParser(prog='gcp-stereo-memory', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--dataset', default='motorcycle')
    ap.add_argument('--frame', help='frame name (default: the first)')
    ap.add_argument('--steps', nargs='+', default=STEPS, metavar='WxH:D|idle',
                    help=f'default: {" ".join(STEPS)}')
    ap.add_argument('-p', '--param', action='append', default=[], metavar='NAME:=VALUE',
                    help='node parameter, as with --ros-args -p; repeatable')
    ap.add_argument('--pipeline', action='store_true',
                    help='measure a StereoPipeline in this process instead of the node')
    args = ap.parse_args(argv)
    frame = load_frame(args.dataset, args.frame or list_frames(args.dataset)[0])
    params = dict(p.split(':=', 1) for p in args.param)
    values = {k: yaml.safe_load(v) for k, v in params.items()}  # as rcl reads them
    if args.pipeline:
        _run_pipeline(args.steps, frame, values)
        return
    with peer_graph('gcp_stereo_memory', params) as (peer, node):
        _run(args.steps, frame, values, peer, node.pid)


def _step(step, values):
    """Return ((width, height), the config of `values` at the step's D) of a step WxH:D."""
    size, d = step.split(':')
    return (tuple(map(int, size.split('x'))),
            config_from_params({**values, 'max_disparity': int(d)}))


def _resized(frame, size):
    return [cv2.resize(im, size, interpolation=cv2.INTER_AREA) for im in (frame.left, frame.right)]


def _run_pipeline(steps, frame, values):
    mmap_large_arrays()  # as the node does
    pipeline = StereoPipeline(config_from_params(values))
    pipeline.with_config(pipeline.config.replace(max_disp=16))(
        *_resized(frame, (64, 48)))  # first calls of Numba and torch
    print(f'{"step":<16}{"peak MB":>9}{"estimate MB":>13}{"ratio":>7}')
    for step in (s for s in steps if s != 'idle'):
        size, config = _step(step, values)
        pipeline = pipeline.with_config(config)
        pair = _resized(frame, size)
        pipeline.release()
        base = rss_mb('self')
        estimate = memory_bytes(config, size[1], size[0]) / MIB
        try:
            pipeline(*pair)
        except ValueError as err:
            print(f'{step:<16}{"refused":>9}{estimate:13.0f}  {err}', flush=True)
            continue
        Path('/proc/self/clear_refs').write_text('5')  # peak := current RSS
        pipeline(*pair)
        peak = rss_mb('self', 'VmHWM') - base
        print(f'{step:<16}{peak:9.0f}{estimate:13.0f}{estimate / peak:7.2f}', flush=True)


def _run(steps, frame, values, peer, pid):
    from rcl_interfaces.msg import Log
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image
    from stereo_msgs.msg import DisparityImage

    pubs = [peer.create_publisher(Image, f'{s}/image_rect', qos_profile_sensor_data)
            for s in ('left', 'right')]
    done, refusals = [], []

    def on_log(msg):
        if msg.name.endswith('gcp_stereo_node') and 'memory_limit_mb' in msg.msg:
            refusals.append(msg.msg)
    peer.create_subscription(DisparityImage, 'disparity',
                             lambda m: done.append(stamp_ns(m.header)), 10)
    peer.create_subscription(Log, '/rosout', on_log, 100)
    client = peer.create_client(SetParameters, 'gcp_stereo_node/set_parameters')
    if not client.wait_for_service(timeout_sec=120):
        raise SystemExit('the node did not come up within 120 s')

    def set_max_disparity(d):
        future = client.call_async(SetParameters.Request(
            parameters=[Parameter('max_disparity', value=d).to_parameter_msg()]))
        while not future.done():
            time.sleep(0.01)

    def send(size):
        """Publish the pair at `size` and wait for the node's answer: 'published' or 'refused'."""
        stamp, seen = time.time_ns(), len(refusals)
        for pub, image in zip(pubs, _resized(frame, size)):
            fields = array_to_image_fields(image, 'rgb8' if image.ndim == 3 else 'mono8')
            msg = Image(**{**fields, 'data': fields['data'].tobytes()})
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
            pub.publish(msg)
        end = time.monotonic() + TIMEOUT_SECONDS
        while time.monotonic() < end:
            if stamp in done:
                return 'published'
            if len(refusals) > seen:
                return 'refused'
            time.sleep(0.05)
        raise SystemExit(f'no answer from the node within {TIMEOUT_SECONDS:g} s')

    wait_for_subscribers(pubs, 120)
    print(f'{"step":<16}{"outcome":<11}{"RSS MB":>8}{"peak MB":>9}{"estimate MB":>13}')
    print(f'{"start":<16}{"":<11}{rss_mb(pid):8.0f}')
    for step in steps:
        Path(f'/proc/{pid}/clear_refs').write_text('5')  # peak := current RSS
        estimate, outcome = '', ''
        if step == 'idle':
            time.sleep(IDLE_SECONDS)
        else:
            size, config = _step(step, values)
            set_max_disparity(config.max_disp)
            estimate = f'{memory_bytes(config, size[1], size[0]) / MIB:13.0f}'
            outcome = send(size)
        print(f'{step:<16}{outcome:<11}{rss_mb(pid):8.0f}{rss_mb(pid, "VmHWM"):9.0f}{estimate}',
              flush=True)


if __name__ == '__main__':
    main()
