"""
What the node did, pair by pair: one record the node updates and its readers only read.

`GcpStereoNode` updates its `NodeStats` as pairs go through: `pair_done` for each pair it
published (a `Sample`, and the stage timings), `error` for each pair skipped or output lost,
`dropped_stale` for each pair a newer one replaced before it was processed. /diagnostics
and the progress log read it: `totals` (counters since the node was activated), `samples`
(the last KEEP_PAIRS pairs) and `trust`. Reading changes nothing; a lock keeps each
snapshot whole across the executor and worker threads. ROS-free.

`trust` says whether the depth of the recent pairs can be trusted:
- recent: the mean over the last RECENT_PAIRS (5) pairs of the share of the valid window
  published and of the mean disparity confidence of what was (`health.published`);
- running level: the median of each over up to LEVEL_PAIRS (100) pairs before those, once
  MIN_LEVEL_PAIRS (5) are there; it follows a lasting change within about LEVEL_PAIRS / 2
  pairs, which ends the warning;
- a warning when a recent value falls below COLLAPSE (half) of its running level, or when a
  view has the same fault (black, saturated, frozen: `health.ViewCheck`) in each of the last
  FAULT_PAIRS (3) pairs. The cause it names: that fault, else what the view check found in
  the newest recent pair with a finding (exposures far apart, no texture) and a
  misalignment beyond MISALIGNED_PX (0.5 px, where doc/alignment.md's error rates start to
  grow), else 'not seen'.
"""
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
import statistics
import threading
from typing import NamedTuple

from ..stereo.health import Finding

RECENT_PAIRS = 5  # pairs averaged into the recent share and confidence
LEVEL_PAIRS = 100  # pairs before those whose median is the running level
MIN_LEVEL_PAIRS = 5  # fewer pairs before the recent ones: no running level yet
COLLAPSE = 0.5  # recent below this fraction of its running level: not to be trusted
FAULT_PAIRS = 3  # the same fault in each of this many last pairs: not to be trusted
MISALIGNED_PX = 0.5  # a misalignment beyond this is named as a cause
KEEP_PAIRS = RECENT_PAIRS + LEVEL_PAIRS  # samples kept


class Sample(NamedTuple):
    """
    One pair published.

    `time`: time.monotonic() when published, s. `latency`: s from the images' stamp to
    publishing on the node's clock (typically 0.1 - 2), None without a clock (use_sim_time
    before /clock). `share`: the share of the valid window published, in [0, 1] (0.75 on
    KITTI 2012 000070), None for an empty window. `confidence`: the mean disparity
    confidence of it, in [0, 1] (0.98 there), None without a fit or with nothing published.
    `findings`: what `health.ViewCheck` found wrong with the views. `misalignment`: px, the
    largest vertical offset of the right view over the image, None when unknown, with
    `misalignment_note` saying why.
    """

    time: float
    latency: float | None
    share: float | None
    confidence: float | None
    findings: tuple[Finding, ...] = ()
    misalignment: float | None = None
    misalignment_note: str = 'not estimated'


class Totals(NamedTuple):
    """
    Counters since the node was activated.

    Pairs `processed` (published), skipped or unpublished (`errors`, the newest reason in
    `last_error`), dropped as `stale`; `stage_seconds` the pipeline's seconds per stage
    summed over the processed pairs (`StereoResult.seconds`' keys).
    """

    processed: int
    errors: int
    stale: int
    last_error: str
    stage_seconds: Mapping[str, float]


class Trust(NamedTuple):
    """
    Whether the recent depth can be trusted (see the module's docstring for the levels).

    `share`, `confidence`: their recent means; `share_level`, `confidence_level`: their
    running levels (each None until known). `views`: the newest pair's findings.
    `misalignment` (px or None) and `misalignment_note`: the newest pair's. `warning`: why
    the depth is not to be trusted, '' when nothing says so; `cause`: what it names, '' then.
    """

    share: float | None
    share_level: float | None
    confidence: float | None
    confidence_level: float | None
    views: tuple[Finding, ...]
    misalignment: float | None
    misalignment_note: str
    warning: str
    cause: str


class NodeStats:
    """The node's counters and its last KEEP_PAIRS samples, safe to update from any thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._samples: deque[Sample] = deque(maxlen=KEEP_PAIRS)
        self._processed = self._errors = self._stale = 0
        self._last_error = ''
        self._stage_seconds: dict[str, float] = {}

    def pair_done(self, sample: Sample, seconds: Mapping[str, float]) -> None:
        """Count a pair published: its `sample` and its seconds per stage."""
        with self._lock:
            self._samples.append(sample)
            self._processed += 1
            for stage, s in seconds.items():
                self._stage_seconds[stage] = self._stage_seconds.get(stage, 0.0) + s

    def error(self, text: str) -> None:
        """Count a pair skipped or its outputs lost, `text` saying why."""
        with self._lock:
            self._errors += 1
            self._last_error = text

    def dropped_stale(self) -> None:
        """Count a pair dropped because a newer one came before it was processed."""
        with self._lock:
            self._stale += 1

    def totals(self) -> Totals:
        """Return the counters as they are now."""
        with self._lock:
            return Totals(self._processed, self._errors, self._stale, self._last_error,
                          dict(self._stage_seconds))

    def samples(self, since: float = -float('inf')) -> tuple[Sample, ...]:
        """Return the kept samples published after `since` (time.monotonic(), s), oldest first."""
        with self._lock:
            return tuple(s for s in self._samples if s.time > since)

    def trust(self) -> Trust:
        """Return whether the depth of the kept samples can be trusted (`trust`)."""
        return trust(self.samples())


def trust(samples: Sequence[Sample]) -> Trust:
    """Return the Trust of `samples`, oldest first (see the module's docstring)."""
    if not samples:
        return Trust(None, None, None, None, (), None, '', '', '')
    recent = samples[-RECENT_PAIRS:]
    before = samples[:-RECENT_PAIRS][-LEVEL_PAIRS:]
    share, share_level = _mean(s.share for s in recent), _level(s.share for s in before)
    confidence = _mean(s.confidence for s in recent)
    confidence_level = _level(s.confidence for s in before)
    fallen = [f'{name} {now:.2f} against its running level {level:.2f}'
              for name, now, level in (('published share of the valid window', share, share_level),
                                       ('disparity confidence', confidence, confidence_level))
              if now is not None and level is not None and now < COLLAPSE * level]
    last = samples[-FAULT_PAIRS:]
    faults = [f.text for f in last[-1].findings
              if f.fault and len(last) == FAULT_PAIRS and all(f in s.findings for s in last)]
    newest = samples[-1]
    warning = cause = ''
    if faults or fallen:
        cause = '; '.join(faults) or _cause(recent)
        said = fallen or [f'{"; ".join(faults)} in each of the last {FAULT_PAIRS} pairs']
        warning = f'depth not to be trusted: {"; ".join(said)}; cause: {cause}'
    return Trust(share, share_level, confidence, confidence_level, newest.findings,
                 newest.misalignment, newest.misalignment_note, warning, cause)


def _cause(recent: Sequence[Sample]) -> str:
    """Name what the recent samples show that lowers what is published; 'not seen' if none."""
    causes = next(([f.text for f in s.findings] for s in reversed(recent) if s.findings), [])
    px = recent[-1].misalignment
    if px is not None and abs(px) > MISALIGNED_PX:
        causes.append(f'rows misaligned by up to {px:.2f} px')
    return '; '.join(causes) or 'not seen'


def _mean(values: Iterable[float | None]) -> float | None:
    """Return the mean of the values that are not None, None if there is none."""
    known = [v for v in values if v is not None]
    return sum(known) / len(known) if known else None


def _level(values: Iterable[float | None]) -> float | None:
    """Return the median of the values that are not None, None if fewer than MIN_LEVEL_PAIRS."""
    known = [v for v in values if v is not None]
    return statistics.median(known) if len(known) >= MIN_LEVEL_PAIRS else None
