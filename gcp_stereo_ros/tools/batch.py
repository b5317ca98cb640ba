"""
gcp-stereo-batch: the pipeline over many bags or dataset frames at once, on Ray.

  --bags DIR_OR_GLOB ... --out DIR   each bag -> DIR/<its name>, as `gcp-stereo-bag run` writes
                                     it (with --png: PNGs in a folder per bag)
  --dataset PATH ...                 each frame -> its rows, as `gcp-stereo-eval` gives them:
                                     the same table, --json file and PNGs (--out)

Ray runs the items, locally by default (a Ray instance started in this process with
--workers processes) or on a running cluster (--address). A worker process builds one
pipeline, whose CNN it loads once, and runs one item at a time on --threads torch, numba and
OpenCV threads; every item asks Ray for --threads CPUs, so a machine runs no more items at
once than its cores allow. Items travel as paths: on a cluster every node must see the inputs
and --out at the same paths (a shared file system) and have this package installed.

An item that fails is reported with its reason and the others go on; the exit status is 1 if
any failed. A rerun skips the items whose output exists (--force redoes them): a bag whose
output bag exists (each is written to a hidden sibling and renamed into place when complete),
a frame whose rows for every method are in the --json file (written every 10 s and at the
end).
"""
import argparse
import contextlib
import glob
import io
import json
import logging
import os
from pathlib import Path
import socket
import sys
import time

import cv2
import numba
try:
    import ray
except ImportError as err:  # an optional extra: say which
    raise ImportError('gcp-stereo-batch runs on Ray, an optional extra of this package: '
                      "pip install 'gcp_stereo_ros[cluster]'") from err
import torch
from tqdm import tqdm

from . import evaluate
from .bag import add_run_options
from .bag.run import convert, run_pipeline
from .cli import console_main, positive_int
from ..ros.params import load_params_file

PROG = 'gcp-stereo-batch'
CORES = os.cpu_count() or 1
JSON_EVERY_SECONDS = 10.0
# Worker processes: no progress bars of their own (tqdm reads this when imported).
RUNTIME_ENV = {'env_vars': {'TQDM_DISABLE': '1'}}

# per worker process: the pipeline or evaluation Runner of each set of options
_cache: dict[object, object] = {}


def _kept(key, make):
    """Return this worker process's object for `key`, made by `make()` on first use."""
    if key not in _cache:
        _cache[key] = make()
    return _cache[key]


def limit_threads(threads):
    """Run torch, numba and OpenCV on `threads` threads in this process."""
    torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    cv2.setNumThreads(threads)


@ray.remote
def bag_task(options, inp, out, png):
    """Write output bag `out` of input bag `inp`; return what `gcp-stereo-bag run` prints."""
    limit_threads(options.threads)
    values = load_params_file(options.params) if options.params else {}
    pipeline = _kept(('bag', options.params), lambda: run_pipeline(values, options.params))
    args = argparse.Namespace(**{**vars(options), 'inp': Path(inp), 'out': Path(out),
                                 'png': png and Path(png)})
    with contextlib.redirect_stdout(io.StringIO()) as log:
        convert(pipeline, values, args)
    return log.getvalue()


@ray.remote
def frame_task(options, source, name):
    """Return the `gcp-stereo-eval` (rows, note) of frame `name` of `source`."""
    limit_threads(options.threads)
    runner = _kept(('eval', options.paths, options.preset, tuple(options.set or ())),
                   lambda: evaluate.make_runner(options))
    return evaluate.evaluate_frame(runner, options, source, name)


# ---- items ------------------------------------------------------------------------------
def _is_bag(path):
    return (path / 'metadata.yaml').is_file() or (
        path.is_file() and path.suffix in ('.mcap', '.db3'))


def find_bags(patterns):
    """
    Return the bags that `patterns` name, each once, in order.

    A pattern is a bag (its folder, or its .mcap / .db3 file), a folder whose non-hidden
    subfolders are bags, or a shell pattern of those. Raises ValueError for a pattern that
    names no bag.
    """
    found = []
    for pattern in patterns:
        bags = []
        for match in sorted(glob.glob(pattern)):
            path = Path(match).resolve()
            if _is_bag(path):
                bags.append(path)
            elif path.is_dir():
                bags += [p for p in sorted(path.iterdir())
                         if not p.name.startswith('.') and p.is_dir() and _is_bag(p)]
        if not bags:
            raise ValueError(f'no bag found in {pattern!r} (a bag is a folder with '
                             'metadata.yaml, or a .mcap / .db3 file)')
        found += [b for b in bags if b not in found]
    return found


def bag_items(args):
    """Return (every item, the items to run): (input bag, output bag, PNG folder or None)."""
    items = []
    for inp in find_bags(args.bags):
        name = inp.stem if inp.is_file() else inp.name
        items.append((str(inp), str(args.out / name), str(args.png / name) if args.png else None))
    _unique([Path(out).name for _, out, _ in items], 'output bag')
    inputs = {inp for inp, _, _ in items}
    clash = [out for _, out, _ in items if out in inputs]
    if clash:
        raise ValueError(f'--out would replace input bags: {", ".join(clash)}')
    return items, [item for item in items if args.force or not Path(item[1]).exists()]


def frame_items(args, rows):
    """
    Return (every item, the items to run): (dataset source, frame name).

    `rows`: {frame name: rows} of an earlier run; a frame with a row for every method is
    not run again.
    """
    sources = [str(Path(s).resolve()) if Path(s).exists() else s for s in args.dataset]
    items = evaluate.select_frames(sources, args.frames)
    _unique([name for _, name in items], 'frame')
    return items, [(source, name) for source, name in items if args.force or not
                   set(args.methods) <= {r['method'] for r in rows.get(name, [])}]


def earlier_rows(args):
    """Return {frame name: rows of args.methods} of an existing --json file (none: {})."""
    if args.force or not args.json or not args.json.exists():
        return {}
    try:
        rows = json.loads(args.json.read_text())
        out = {}
        for r in rows:
            if r['method'] in args.methods:
                out.setdefault(r['frame'], []).append(r)
    except (ValueError, TypeError, KeyError) as err:
        raise ValueError(f'{args.json} holds no gcp-stereo-eval rows ({err}); '
                         'pass --force to replace it') from None
    return out


def _unique(names, what):
    seen = set()
    twice = sorted({n for n in names if n in seen or seen.add(n)})
    if twice:
        raise ValueError(f'{what} names must be unique, found twice: {", ".join(twice)}')


# ---- running ----------------------------------------------------------------------------
def start_ray(args):
    """
    Connect to Ray, as --address says; return whether this call started it.

    A Ray instance already initialized in this process is used as it is.
    """
    if ray.is_initialized():
        return False
    if args.address:
        host, _, port = args.address.rpartition(':')
        if host and port.isdigit():  # Ray itself retries an unreachable HOST:PORT for minutes
            try:
                socket.create_connection((host, int(port)), timeout=10).close()
            except OSError as err:
                raise ConnectionError(f'no Ray cluster at {args.address}: {err}') from None
        try:
            ray.init(address=args.address, runtime_env=RUNTIME_ENV,
                     logging_level=logging.WARNING)
        except ConnectionError as err:  # e.g. the cluster's token missing here: say why
            if err.__cause__:
                err.add_note(str(err.__cause__).strip().splitlines()[-1])
            raise
    else:
        # 'local': a new instance, even where `ray start` left a cluster to join by default
        ray.init(address='local', num_cpus=args.workers * args.threads, include_dashboard=False,
                 runtime_env=RUNTIME_ENV, logging_level=logging.WARNING)
    return True


def _reason(err):
    """One line saying why an item failed."""
    cause = err.cause if isinstance(err, ray.exceptions.RayTaskError) else err
    return f'{type(cause).__name__}: {cause}'.splitlines()[0]


def run_items(refs, label, done):
    """
    Wait for every task of `refs` ({ObjectRef: item}), calling done(item, result) as each ends.

    Returns [(label(item), reason)] of the failed ones, each also reported when it fails.
    """
    failed = []
    pending = list(refs)
    with tqdm(total=len(refs), unit='item', smoothing=0) as bar:
        while pending:
            (ref,), pending = ray.wait(pending, num_returns=1)
            item = refs[ref]
            try:
                result = ray.get(ref)
            except ray.exceptions.RayError as err:
                failed.append((label(item), _reason(err)))
                tqdm.write(f'{PROG}: {label(item)} failed: {failed[-1][1]}', file=sys.stderr)
            else:
                done(item, result)
            bar.update()
    return failed


def run_bags(args, todo):
    task = bag_task.options(num_cpus=args.threads)
    refs = {task.remote(args, *item): item for item in todo}
    return run_items(refs, lambda item: item[0], lambda item, log: tqdm.write(log.rstrip()))


def run_frames(args, items, todo, rows):
    """Evaluate the frames `todo`, adding their rows to `rows`; write --json as they come."""
    last = time.monotonic()
    notes = {}

    def ordered():  # as gcp-stereo-eval orders them
        return [r for _, name in items for r in rows.get(name, [])]

    def done(item, result):
        nonlocal last
        rows[item[1]], notes[item[1]] = result
        if args.json and time.monotonic() - last > JSON_EVERY_SECONDS:
            evaluate.write_rows(args.json, ordered())
            last = time.monotonic()

    task = frame_task.options(num_cpus=args.threads)
    refs = {task.remote(args, *item): item for item in todo}
    failed = run_items(refs, lambda item: item[1], done)
    if rows:
        evaluate.print_results(ordered(), args.methods, notes)
    if args.json:
        evaluate.write_rows(args.json, ordered())
    return failed


# ---- command line -----------------------------------------------------------------------
def parser():
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    bags = ap.add_argument_group('bags (as gcp-stereo-bag run)')
    bags.add_argument('--bags', nargs='+', metavar='DIR_OR_GLOB',
                      help='bags (folders, or their .mcap / .db3 files), folders of bags, or '
                           'shell patterns of them (quoted)')
    add_run_options(bags)
    frames = ap.add_argument_group('dataset frames (as gcp-stereo-eval)')
    evaluate.add_options(frames, dataset_required=False)
    ap.add_argument('--out', type=Path, metavar='DIR',
                    help='bags: write the output bags here (required); frames: write '
                         'colour-mapped disparity PNGs here')
    ap.add_argument('--force', action='store_true',
                    help='redo the items whose output exists (default: skip them)')
    cluster = ap.add_argument_group('Ray')
    cluster.add_argument('--address', metavar='HOST:PORT',
                         help="join this running Ray cluster (or 'auto': the one started on "
                              'this machine by `ray start`) instead of starting Ray here')
    cluster.add_argument('--workers', type=positive_int,
                         help=f'local Ray: worker processes (default: the cores, {CORES})')
    cluster.add_argument('--threads', type=positive_int,
                         help='compute threads per worker, and the CPUs each item asks Ray for '
                              '(default: cores // workers locally, 1 on a cluster)')
    return ap


def parse_args(argv):
    ap = parser()
    args = ap.parse_args(argv)
    if bool(args.bags) == bool(args.dataset):
        ap.error('give either --bags or --dataset')
    if args.bags and not args.out:
        ap.error('--bags needs --out DIR')
    other = ('frames', 'max_disp', 'set', 'json') if args.bags else ('params', 'png')
    for name in other:
        if getattr(args, name):
            ap.error(f'--{name.replace("_", "-")} does not apply to '
                     f'{"--bags" if args.bags else "--dataset"}')
    if args.address and args.workers:
        ap.error('--workers is for a local Ray; on a cluster, --threads sets how many items '
                 'a machine runs at once (its CPUs // threads)')
    for name in ('out', 'png', 'params', 'json'):  # paths the workers see as the driver does
        if getattr(args, name):
            setattr(args, name, getattr(args, name).resolve())
    args.workers = args.workers or CORES
    args.threads = args.threads or (1 if args.address else max(1, CORES // args.workers))
    return args


@console_main(PROG)
def main(argv: list[str] | None = None) -> int | None:
    args = parse_args(argv)
    rows = {}
    if args.bags:  # settings and weights are checked here once, not by every item
        run_pipeline(load_params_file(args.params) if args.params else {}, args.params)
        items, todo = bag_items(args)
        args.out.mkdir(parents=True, exist_ok=True)
    else:
        evaluate.make_runner(args)
        rows = earlier_rows(args)
        items, todo = frame_items(args, rows)
    skipped = len(items) - len(todo)
    if skipped:
        print(f'{PROG}: skipping {skipped} item(s) whose output exists (--force redoes them)')
    started = start_ray(args) if todo else False
    try:
        failed = (run_bags(args, todo) if args.bags else
                  run_frames(args, items, todo, rows))
    finally:
        if started:
            ray.shutdown()
    print(f'{PROG}: {len(todo) - len(failed)} done, {skipped} skipped, {len(failed)} failed')
    for label, reason in failed:
        print(f'{PROG}: failed: {label}: {reason}', file=sys.stderr)
    return 1 if failed else None


if __name__ == '__main__':
    # Run the module under its own name: Ray workers import the tasks from there.
    from gcp_stereo_ros.tools import batch
    sys.exit(batch.main())
