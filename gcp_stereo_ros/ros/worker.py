"""A worker thread that processes only the newest item handed to it."""
import threading


class NewestWorker:
    """
    Run `process(*item)` in a thread for the newest item `put` since it last looked.

    An item still waiting when a newer one arrives is dropped and counted in `stale`, so
    the caller never falls behind and memory holds at most one waiting item. `on_idle()`
    is called from the thread each time it has nothing left to do, and `on_quiet()` once no
    item has come for `quiet_seconds` since the last one (the node lets go of its arrays
    then). The thread outlives any exception of these: it goes to `on_error(err)`.
    """

    def __init__(self, process, name, on_error, on_idle=lambda: None, on_quiet=None,
                 quiet_seconds=2.0):
        self._process = process
        self._on_error = on_error
        self._on_idle = on_idle
        self._on_quiet = on_quiet
        self._quiet_seconds = quiet_seconds
        self.stale = 0
        self._pending = None
        self._working = False
        self._stopping = False
        self._cv = threading.Condition()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def idle(self):
        """Return True while no item is waiting or being processed."""
        with self._cv:
            return self._pending is None and not self._working

    def put(self, item):
        """Hand over `item`, replacing (and counting) one still waiting."""
        with self._cv:
            if self._pending is not None:
                self.stale += 1
            self._pending = item
            self._cv.notify()

    def stop(self, timeout=None):
        """
        Drop waiting items and wait up to `timeout` s for the item in progress, if any.

        Return True if the thread has ended.
        """
        with self._cv:
            self._stopping = True
            self._cv.notify()
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def _run(self):
        quiet_due = False  # an item was processed and on_quiet has not run since
        while True:
            with self._cv:
                ready = self._cv.wait_for(lambda: self._pending is not None or self._stopping,
                                          self._quiet_seconds if quiet_due else None)
                if self._stopping:
                    return
                if ready:
                    item, self._pending = self._pending, None
                    self._working = True
            if not ready:
                quiet_due = False
                self._call(self._on_quiet)
                continue
            self._call(self._process, *item)
            with self._cv:
                self._working = False
                idle = self._pending is None and not self._stopping
            if idle:
                self._call(self._on_idle)
            quiet_due = self._on_quiet is not None

    def _call(self, fn, *args):
        try:
            fn(*args)
        except Exception as err:  # whatever failed, the thread goes on: say why
            self._on_error(err)
