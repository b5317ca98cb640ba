"""A worker thread that processes only the newest item handed to it."""
import threading


class NewestWorker:
    """
    Run `process(*item)` in a thread for the newest item `put` since it last looked.

    An item still waiting when a newer one arrives is dropped and counted in `stale`, so
    the caller never falls behind and memory holds at most one waiting item. `on_idle()`
    is called from the thread each time it has nothing left to do.
    """

    def __init__(self, process, name, on_idle=lambda: None):
        self._process = process
        self._on_idle = on_idle
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

    def stop(self):
        """Stop after the item in progress, if any; waiting items are dropped."""
        with self._cv:
            self._stopping = True
            self._cv.notify()
        self._thread.join()

    def _run(self):
        while True:
            with self._cv:
                while self._pending is None and not self._stopping:
                    self._cv.wait()
                if self._stopping:
                    return
                item, self._pending = self._pending, None
                self._working = True
            try:
                self._process(*item)
            finally:
                with self._cv:
                    self._working = False
                    idle = self._pending is None and not self._stopping
                if idle:
                    self._on_idle()
