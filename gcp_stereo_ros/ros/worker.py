"""A worker thread that processes only the newest item handed to it."""
from collections.abc import Callable
import threading


class NewestWorker:
    """
    Run `process(*item)` in a thread for the newest item `put` since it last looked.

    An item still waiting when a newer one arrives is dropped and `on_stale()` called, so
    the caller never falls behind and memory holds at most one waiting item. `on_idle()`
    is called from the thread each time it has nothing left to do, and `on_quiet()` once no
    item has come for `quiet_seconds` since the last one (the node lets go of its arrays
    then). The thread outlives any exception of these: it goes to `on_error(err)`.
    """

    def __init__(self, process: Callable[..., object], name: str,
                 on_error: Callable[[Exception], object],
                 on_idle: Callable[[], object] = lambda: None,
                 on_quiet: Callable[[], object] | None = None,
                 on_stale: Callable[[], object] = lambda: None,
                 quiet_seconds: float = 2.0) -> None:
        self._process = process
        self._on_error = on_error
        self._on_idle = on_idle
        self._on_quiet = on_quiet
        self._on_stale = on_stale
        self._quiet_seconds = quiet_seconds
        self._pending: tuple | None = None
        self._working = False
        self._stopping = False
        self._cv = threading.Condition()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def idle(self) -> bool:
        """Return True while no item is waiting or being processed."""
        with self._cv:
            return self._pending is None and not self._working

    def put(self, item: tuple) -> None:
        """Hand over `item`, replacing one still waiting (and calling `on_stale()` then)."""
        with self._cv:
            replaced = self._pending is not None
            self._pending = item
            self._cv.notify()
        if replaced:
            self._call(self._on_stale)

    def stop(self, timeout: float | None = None) -> bool:
        """
        Drop waiting items and wait up to `timeout` s for the item in progress, if any.

        Return True if the thread has ended.
        """
        with self._cv:
            self._stopping = True
            self._cv.notify()
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def _run(self) -> None:
        quiet_due = False  # an item was processed and on_quiet has not run since
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._pending is not None or self._stopping,
                                  self._quiet_seconds if quiet_due else None)
                if self._stopping:
                    return
                item, self._pending = self._pending, None
                self._working = item is not None
            if item is None:  # quiet for quiet_seconds, only waited for with on_quiet
                quiet_due = False
                if self._on_quiet is not None:
                    self._call(self._on_quiet)
                continue
            self._call(self._process, *item)
            with self._cv:
                self._working = False
                idle = self._pending is None and not self._stopping
            if idle:
                self._call(self._on_idle)
            quiet_due = self._on_quiet is not None

    def _call(self, fn: Callable[..., object], *args: object) -> None:
        try:
            fn(*args)
        except Exception as err:  # whatever failed, the thread goes on: say why
            self._on_error(err)
