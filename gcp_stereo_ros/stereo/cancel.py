"""Stopping a run from another thread: a flag the kernels read once per row."""
import numpy as np
import numpy.typing as npt


class Cancelled(Exception):
    """A run stopped because its CancelFlag was set."""


class CancelFlag:
    """
    A flag that one thread sets to stop a run in another.

    The Numba kernels take `array` (one uint8) and skip their remaining rows once it is 1;
    they release the GIL, so the setting thread runs meanwhile. Between stages the pipeline
    calls `check`. A flag stays set until `clear`.
    """

    def __init__(self) -> None:
        self.array = np.zeros(1, np.uint8)

    def set(self) -> None:  # noqa: A003 (the threading.Event name)
        self.array[0] = 1

    def clear(self) -> None:
        self.array[0] = 0

    def is_set(self) -> bool:
        return bool(self.array[0])

    def check(self) -> None:
        """Raise Cancelled if the flag is set."""
        if self.array[0]:
            raise Cancelled('cancelled')


def flag_array(cancel: CancelFlag | None) -> npt.NDArray[np.uint8]:
    """Return the array the kernels read for `cancel`, a CancelFlag or None (never set)."""
    return (cancel or CancelFlag()).array
