"""
gcp-stereo-load: feed the node a camera-rate stream and report whether it keeps up.

Starts `gcp_stereo_node` as its own process in a private ROS graph, publishes one real pair
back to back (left, then right) at `--rate` Hz for `--seconds`, and reports pairs sent and
processed (the rest were dropped as stale), latency from publishing to receiving the
disparity (median, max), the node's RSS over the run (it should stay flat) and its CPU
time: the whole process, and its executor thread, which takes the images (% of one core).
`--stamps repeat` sends every pair with one stamp, as a one-frame bag played with --loop
does (no latency then: the stamps do not tell the pairs apart).

With --steps it walks the node through image sizes and disparity ranges instead: a step
WxH:D sets max_disparity to D, publishes the pair resized to WxH once and waits for its
disparity or the node's refusal; `idle` waits 3 s (the node lets its arrays go after 2 s
without input). After each step it prints the node's RSS and its peak during the step
(/proc/<pid>/status; the peak is reset through /proc/<pid>/clear_refs, Linux only) beside
the pipeline's estimate for the pair (`memory_bytes`), which the node compares with
memory_limit_mb. With --steps and --pipeline it measures a StereoPipeline in this process,
without ROS: per step the peak RSS of a second pair of that size above the process without
kept arrays, as a stream of such pairs needs it, against the estimate.
"""
import argparse
import json
import os
from pathlib import Path
import re
import statistics
import sys
import threading
import time

import cv2
import yaml

from .bag.play import wait_for_subscribers
from .cli import console_main, positive
from ..evaluation.datasets import list_frames, load_frame
from ..ros.graph import peer_graph
from ..ros.messages import stamp_ns
from ..ros.params import config_from_params, load_params_file
from ..ros.rosimage import array_to_image_fields
from ..stereo.memory import memory_bytes, MIB, mmap_large_arrays
from ..stereo.pipeline import StereoPipeline

IDLE_SECONDS = 3.0
ANSWER_SECONDS = 600.0


def rss_mb(pid, key='VmRSS'):
    """Return the resident memory of process `pid` in MiB (`key` 'VmHWM': its peak)."""
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith(key + ':'):
            return int(line.split()[1]) / 1024.0
    return float('nan')


def reset_peak_rss(pid):
    """Make the peak resident memory ('VmHWM') of process `pid` its current RSS (Linux)."""
    Path(f'/proc/{pid}/clear_refs').write_text('5')


def cpu_seconds(pid, tid=None):
    """Return the user + system CPU seconds of process `pid` (of its thread `tid` if given)."""
    path = f'/proc/{pid}/task/{tid}/stat' if tid else f'/proc/{pid}/stat'
    fields = Path(path).read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def node_param(text):
    """Argparse type: `NAME:=VALUE` -> (NAME, VALUE)."""
    name, sep, value = text.partition(':=')
    if not (name and sep):
        raise argparse.ArgumentTypeError(f'expected NAME:=VALUE, got {text!r}')
    return name, value


def step_arg(text):
    """Argparse type: 'idle' or WxH:D, e.g. 1920x1080:256."""
    if not re.fullmatch(r'idle|[0-9]+x[0-9]+:[0-9]+', text):
        raise argparse.ArgumentTypeError(f"expected 'idle' or WIDTHxHEIGHT:D, got {text!r}")
    return text


@console_main('gcp-stereo-load')
def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog='gcp-stereo-load', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--dataset', default='motorcycle')
    ap.add_argument('--frame', help='frame name (default: the first)')
    ap.add_argument('--rate', type=positive, default=30.0)
    ap.add_argument('--seconds', type=positive, default=60.0)
    ap.add_argument('--stamps', choices=('fresh', 'repeat'), default='fresh',
                    help='a new stamp for every pair (default), or one stamp for all, as a '
                         'looped one-frame bag')
    ap.add_argument('--params', type=Path, metavar='FILE',
                    help='node parameters file, as with --ros-args --params-file (e.g. '
                         'config/gcp_stereo_realtime.yaml); -p overrides it')
    ap.add_argument('-p', '--param', action='append', default=[], type=node_param,
                    metavar='NAME:=VALUE',
                    help='node parameter, as with --ros-args -p; repeatable')
    ap.add_argument('--json', type=Path)
    ap.add_argument('--steps', nargs='+', type=step_arg, metavar='WxH:D|idle',
                    help='walk the node through these sizes and disparity ranges and report '
                         'its memory, e.g. 640x480:128 idle 1920x1080:256 idle')
    ap.add_argument('--pipeline', action='store_true',
                    help='with --steps: measure a StereoPipeline in this process instead')
    args = ap.parse_args(argv)

    frame = load_frame(args.dataset, args.frame or list_frames(args.dataset)[0])
    params = {'max_disparity': frame.max_disp, **dict(args.param)}
    if args.steps:
        values = {**(load_params_file(args.params) if args.params else {}),
                  **{k: yaml.safe_load(str(v)) for k, v in params.items()}}  # as rcl reads them
        if args.pipeline:
            return _walk_pipeline(args.steps, frame, values)
        with peer_graph('gcp_stereo_load', params, args.params) as (peer, node):
            return _walk_node(args.steps, frame, values, peer, node.pid)
    with peer_graph('gcp_stereo_load', params, args.params) as (peer, node):
        report = _measure(args, frame, peer, node)
    for key, value in report.items():
        print(f'{key:<21} {value}')
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
    sent, latency, outputs = {}, [], []
    lock = threading.Lock()

    def on_disparity(msg):
        stamp = stamp_ns(msg.header)
        with lock:
            outputs.append(stamp)
            if stamp in sent and args.stamps == 'fresh':
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
    while not outputs and time.monotonic() < deadline and node.poll() is None:
        publish(time.time_ns())
        time.sleep(1.0)
    if node.poll() is not None:
        raise ChildProcessError(f'the node exited with status {node.returncode}')
    if not outputs:
        raise TimeoutError('the node produced no disparity within 120 s')
    time.sleep(3.0)  # the warm-up pairs still in flight
    with lock:
        sent.clear()
        latency.clear()
        outputs.clear()
    rss = [rss_mb(node.pid)]
    cpu = (cpu_seconds(node.pid), cpu_seconds(node.pid, node.pid))
    start = time.monotonic()
    repeated = time.time_ns()
    n = 0
    while time.monotonic() - start < args.seconds:
        publish(time.time_ns() if args.stamps == 'fresh' else repeated)
        n += 1
        if n % max(1, int(args.rate * 10)) == 0:
            rss.append(rss_mb(node.pid))
        time.sleep(max(0.0, start + n / args.rate - time.monotonic()))
    cpu = [100 * (now - then) / (time.monotonic() - start)
           for now, then in zip((cpu_seconds(node.pid), cpu_seconds(node.pid, node.pid)), cpu)]
    time.sleep(3.0)  # let the last frame through
    rss.append(rss_mb(node.pid))
    return {
        'frame': frame.name, 'size': list(frame.left.shape[:2][::-1]), 'rate_hz': args.rate,
        'seconds': args.seconds, 'stamps': args.stamps, 'pairs_sent': n,
        'pairs_processed': len(outputs), 'pairs_dropped': n - len(outputs),
        'latency_median_s': statistics.median(latency) if latency else None,
        'latency_max_s': max(latency) if latency else None,
        'rss_mb': [round(r, 1) for r in rss], 'node_cpu_percent': round(cpu[0], 1),
        'executor_cpu_percent': round(cpu[1], 1),
    }


def _step(step, values):
    """Return ((width, height), the config of `values` at the step's D) of a step WxH:D."""
    size, d = step.split(':')
    return (tuple(map(int, size.split('x'))),
            config_from_params({**values, 'max_disparity': int(d)}))


def _resized(frame, size):
    return [cv2.resize(im, size, interpolation=cv2.INTER_AREA) for im in (frame.left, frame.right)]


def _walk_pipeline(steps, frame, values):
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
        reset_peak_rss('self')
        pipeline(*pair)
        peak = rss_mb('self', 'VmHWM') - base
        print(f'{step:<16}{peak:9.0f}{estimate:13.0f}{estimate / peak:7.2f}', flush=True)


def _walk_node(steps, frame, values, peer, pid):
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
        raise TimeoutError('the node did not come up within 120 s')

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
            msg.header.frame_id = 'left'
            pub.publish(msg)
        end = time.monotonic() + ANSWER_SECONDS
        while time.monotonic() < end:
            if stamp in done:
                return 'published'
            if len(refusals) > seen:
                return 'refused'
            time.sleep(0.05)
        raise TimeoutError(f'no answer from the node within {ANSWER_SECONDS:g} s')

    wait_for_subscribers(pubs, 120)
    print(f'{"step":<16}{"outcome":<11}{"RSS MB":>8}{"peak MB":>9}{"estimate MB":>13}')
    print(f'{"start":<16}{"":<11}{rss_mb(pid):8.0f}')
    for step in steps:
        reset_peak_rss(pid)
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
    sys.exit(main())
