"""
A rig's misalignment followed over frames, as the node runs it: smoothed, judged and paced.

`DriftTracker` smooths the per-frame `alignment.Misalignment` estimates (a drift is slow):
each term's mean weighted by the inverse of its variance, older estimates fading, restarted
when the rig jumps; it says which correction to apply and its level (OK, WARN, ERROR).
`Cadence` says when the next estimate is due so that the alignment costs at most a share of
the frames' time, and `Background` runs the estimates on a thread of their own so that the
frames never wait for one (nor does a GPU). `Monitor` is the three as the node and the bag
tool use them. ROS-free; the manual's page is doc/alignment.md.
"""
from collections.abc import Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
import threading
import time
from typing import Any

import numpy as np
import numpy.typing as npt

from .alignment import basis, estimate, grid, MAX_CORRECTION, MIN_CORRECTION, Misalignment, TERMS
from .config import StereoConfig
from .images import gray_pair

MEMORY = 5.0  # estimates: an estimate's weight falls by 1 / MEMORY at each newer one
FLOOR = 0.02  # px, added in quadrature to each term's standard error (scene-to-scene spread)
JUMP = 0.5  # px beyond 3 standard errors: a change of the field this large is a jump
WARN = 1.0  # px of misalignment (the largest abs(v)) from which the level is WARN
ERROR = MAX_CORRECTION  # px beyond which the level is ERROR: too large to correct
BUDGET = 0.05  # the share of the frames' time the estimates and corrections may take
LEVELS = ('OK', 'WARN', 'ERROR')


@dataclass(frozen=True)
class DriftStatus:
    """
    What the node reports of the misalignment: `level` of LEVELS, `px` and a `message`.

    `px` is the largest abs(v) over the image of the smoothed estimate's supported terms
    (None while unknown, `message` then saying why), e.g. 0.45 for a KITTI 2015 pair.
    """

    level: str
    px: float | None
    message: str


def _fitted(m: Misalignment) -> npt.NDArray[np.bool_]:
    """Return which of TERMS the estimate fitted (a coefficient or a standard error)."""
    return (np.asarray(m.fitted) != 0) | (np.asarray(m.errors) != 0)


class DriftTracker:
    """
    The misalignment smoothed over a stream of estimates, and the correction it asks for.

    Each term's estimate weighs 1 / (error^2 + FLOOR^2); the weights of the earlier ones are
    multiplied by 1 - 1 / `memory` at each new one. An estimate whose field differs from the
    smoothed one by more than `jump` px plus 3 standard errors somewhere is held; the next
    that agrees with it (not with the smoothed one) restarts the smoothing from the two, so
    a single wrong estimate changes nothing. Unknown estimates leave it as it is.
    """

    def __init__(self, memory: float = MEMORY, jump: float = JUMP, warn: float = WARN,
                 error: float = ERROR, min_correction: float = MIN_CORRECTION) -> None:
        """Make an empty tracker (unknown); the arguments as the module's constants say."""
        self.memory, self.jump, self.warn, self.error = memory, jump, warn, error
        self.min_correction = min_correction
        self.reset('no estimate yet')

    def reset(self, reason: str) -> None:
        """Forget every estimate: unknown, for `reason`."""
        self._weight = np.zeros(len(TERMS))  # sum of the weights per term
        self._sum = np.zeros(len(TERMS))  # sum of weight * coefficient per term
        self._shape: tuple[int, int] | None = None
        self._held: Misalignment | None = None
        self._why = reason
        self.estimates = 0  # known estimates since the last restart
        self.unknown_run = 0  # unknown estimates since the last known one

    def update(self, m: Misalignment) -> None:
        """Take one frame's estimate (known or not)."""
        if not m.known:
            self.unknown_run += 1
            self._why = m.reason
            return
        self.unknown_run = 0
        if self._shape != m.shape:
            self.reset('the image size changed')
            self._add(m)
        elif not self._apart(m, self.current):
            self._held = None
            self._add(m)
        elif self._held is not None and not self._apart(m, self._held):
            held = self._held
            self.reset('a jump')
            self._add(held)
            self._add(m)
        else:
            self._held = m

    @property
    def held(self) -> bool:
        """Return whether an estimate that jumped waits for the next one to confirm it."""
        return self._held is not None

    def _add(self, m: Misalignment) -> None:
        """Fold the known estimate `m` into the smoothed one."""
        used = _fitted(m)
        w = np.where(used, 1 / (np.square(m.errors) + FLOOR ** 2), 0.0)
        fade = 1 - 1 / self.memory if self.estimates else 0.0
        self._weight = fade * self._weight + w
        self._sum = fade * self._sum + w * np.asarray(m.fitted)
        self._shape = m.shape
        self.estimates += 1

    def _apart(self, a: Misalignment, b: Misalignment) -> bool:
        """Return whether the fields of a and b differ by more than `jump` + 3 errors."""
        g = basis(*grid(a.shape), a.shape).reshape(-1, len(TERMS))
        diff = np.abs(g @ (np.asarray(a.fitted) - np.asarray(b.fitted)))
        sigma = np.sqrt(np.square(g) @ (np.square(a.errors) + np.square(b.errors)))
        return bool((diff > self.jump + 3 * sigma).any())

    @property
    def current(self) -> Misalignment:
        """Return the smoothed estimate (its `coefficients`: the supported terms), or unknown."""
        if self._shape is None:
            return Misalignment(False, reason=self._why, cause='none')
        used = self._weight > 0
        fitted = np.where(used, self._sum / np.where(used, self._weight, 1), 0.0)
        errors = np.where(used, 1 / np.sqrt(np.where(used, self._weight, 1)), 0.0)
        return Misalignment(True, tuple(map(float, fitted)), tuple(map(float, errors)),
                            self._shape, matches=self.estimates)

    def correction(self) -> Misalignment:
        """Return the estimate to correct the pair with; an unknown one saying why not."""
        m = self.current
        verdict = m.verdict(self.min_correction, self.error)
        if verdict == 'corrected':
            return m
        return Misalignment(False, shape=m.shape, reason=verdict, cause='none')

    def status(self) -> DriftStatus:
        """Return the level of the smoothed misalignment: OK, WARN from `warn`, ERROR."""
        m = self.current
        if not m.known:
            return DriftStatus('OK', None, self._why)
        px = m.largest
        note = (f'; the last {self.unknown_run} estimates unknown: {self._why}'
                if self.unknown_run else '')
        if px > self.error:
            return DriftStatus('ERROR', px, f'{px:.2f} px: too large to correct (over '
                               f'{self.error:g} px), recalibrate{note}')
        done = 'corrected' if px >= self.min_correction else 'not resampled'
        if px >= self.warn:
            return DriftStatus('WARN', px, f'{px:.2f} px ({done}): the rig has drifted, '
                               f'recalibrate{note}')
        return DriftStatus('OK', px, f'{px:.2f} px ({done}){note}')


class Cadence:
    """
    When the next estimate is due, so that the alignment takes at most `budget` of the time.

    Each frame earns `budget` times its seconds, less what its correction took; an estimate
    is due once the credit covers the last one's cost (the first at once). The credit is
    capped at two estimates, so that an idle spell brings no burst.
    """

    def __init__(self, budget: float = BUDGET) -> None:
        """Make a cadence that lets the alignment take `budget` (0-1) of the frames' time."""
        self.budget = budget
        self.credit = 0.0
        self.cost: float | None = None  # seconds, the last estimate's

    def frame(self, seconds: float, spent: float = 0.0) -> None:
        """Count a frame of `seconds`, of which the alignment (its correction) `spent`."""
        cap = 2 * (self.cost or 0.0)
        self.credit = min(self.credit + self.budget * seconds - spent, cap)

    def due(self) -> bool:
        """Return whether the next estimate may run now."""
        return self.cost is None or self.credit >= self.cost

    def spent(self, seconds: float) -> None:
        """Count an estimate that took `seconds`."""
        self.credit -= seconds
        self.cost = seconds


class Background:
    """
    Runs one estimate at a time on a thread of its own; the caller collects it when done.

    OpenCV and NumPy release the GIL for most of an estimate, so the frames go on meanwhile.
    """

    def __init__(self) -> None:
        """Start the thread (lazily, with the first estimate)."""
        self._pool = ThreadPoolExecutor(1, thread_name_prefix='alignment')
        self._job: Future[tuple[Misalignment, float]] | None = None

    @property
    def busy(self) -> bool:
        """Return whether an estimate is running or waits to be collected."""
        return self._job is not None

    def submit(self, left: npt.ArrayLike, right: npt.ArrayLike, max_disp: int) -> bool:
        """Start `estimate(left, right, max_disp)` unless one is running; return if started."""
        if self._job is not None:
            return False
        self._job = self._pool.submit(_timed, left, right, max_disp)
        return True

    def collect(self) -> tuple[Misalignment, float] | None:
        """
        Return (the estimate, its seconds) once done, then forget it; None before.

        An estimate that failed is unknown, its error the reason (the frames go on).
        """
        if self._job is None or not self._job.done():
            return None
        job, self._job = self._job, None
        try:
            return job.result()
        except Exception as err:  # any failure of the thread's estimate
            return Misalignment(False, reason=f'the estimate failed: {err}', cause='none'), 0.0

    def close(self) -> None:
        """Stop the thread (after the running estimate, which is dropped)."""
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._job = None


def _timed(left: npt.ArrayLike, right: npt.ArrayLike, max_disp: int
           ) -> tuple[Misalignment, float]:
    """Return the estimate of the pair and its wall time in seconds."""
    t = time.perf_counter()
    m = estimate(left, right, max_disp)
    return m, time.perf_counter() - t


class Monitor:
    """
    The alignment of a stream of pairs, as the node runs it: estimated, smoothed, applied.

    `before` each pair collects a finished estimate, starts the next when the `Cadence`
    lets it or a jump waits to be confirmed (on the `Background` thread, or inline with
    `every`: each pair, as the bag tool does) and returns the correction for the pipeline;
    `after` counts the pair's time. A pair is estimated only once it is found to be one
    the pipeline takes (`images.gray_pair`: one size, finite): else `before` raises its
    ValueError, as the pipeline would. `status` may be read from another thread.
    """

    def __init__(self, every: bool = False) -> None:
        """Make a monitor; `every`: estimate every pair, inline (deterministic)."""
        self.tracker = DriftTracker()
        self.cadence = Cadence()
        self.background = None if every else Background()
        self.on = True  # the config's align
        self.last: Misalignment | None = None  # the newest estimate collected by `before`
        self._lock = threading.Lock()
        self._start = time.perf_counter()

    def before(self, left: npt.ArrayLike, right: npt.ArrayLike, config: StereoConfig,
               values: Mapping[str, Any]) -> Misalignment | None:
        """
        Return the misalignment the pipeline is to undo in this pair (None without align).

        `values`: the node's parameters (align_warn_px, align_error_px, align_budget; the
        module's constants where missing).
        """
        self._start = time.perf_counter()
        self.on = config.align
        if not self.on:
            return None
        t = self.tracker
        t.warn, t.error = values.get('align_warn_px', WARN), values.get('align_error_px', ERROR)
        self.cadence.budget = values.get('align_budget', BUDGET)
        done = (_timed(left, right, config.max_disp) if self.background is None
                else self.background.collect())
        with self._lock:
            if done is not None:
                self.last = done[0]
                t.update(done[0])
                self.cadence.spent(done[1])
            correction = t.correction()
        if self.background is not None and (self.cadence.due() or t.held):
            self.background.submit(*gray_pair(left, right), config.max_disp)
        return correction

    def after(self, align_seconds: float) -> None:
        """Count the pair since `before`, of which the correction took `align_seconds`."""
        self.cadence.frame(time.perf_counter() - self._start, align_seconds)

    def status(self) -> DriftStatus:
        """Return the smoothed misalignment's level ('OK', None px without align)."""
        if not self.on:
            return DriftStatus('OK', None, 'align is off')
        with self._lock:
            return self.tracker.status()

    def close(self) -> None:
        """Stop the background thread."""
        if self.background is not None:
            self.background.close()
