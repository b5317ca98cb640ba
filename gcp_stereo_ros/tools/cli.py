"""
What every console script shares: its exit status, one-line errors and option types.

A tool's `main(argv=None)` is decorated with `console_main(prog)`: it then returns 0 when
`main` returns None, and an expected error (a missing or unreadable file, an unknown frame,
a bad value: ValueError, OSError and the tool's own `errors`) becomes one line on stderr,
`prog: error: message`, and exit status 1, as argparse reports bad options (status 2).
Notes added to the error (`err.add_note`) end the line. Ctrl-C is `prog: interrupted`,
status 130, and SIGTERM `prog: terminated`, status 143, both raised in the main thread so
that every `finally` (a bag's staging folder, say) runs first. Anything else is a bug and
keeps its traceback.
"""
import argparse
from collections.abc import Callable
import functools
import signal
import sys
import threading
from types import FrameType
from typing import Protocol

# A tool's main(argv): its exit status, None for 0.
Main = Callable[[list[str] | None], int | None]


class Entry(Protocol):
    """A console script's entry: main(argv=None) -> the exit status."""

    def __call__(self, argv: list[str] | None = None) -> int: ...


class Terminated(BaseException):
    """SIGTERM, raised like KeyboardInterrupt."""


def _terminate(signum: int, frame: FrameType | None) -> None:
    raise Terminated


def console_main(prog: str,
                 errors: tuple[type[Exception], ...] = ()) -> Callable[[Main], Entry]:
    """Return a decorator making `main(argv=None)` a console-script entry (see the module)."""
    expected: tuple[type[Exception], ...] = (ValueError, OSError, *errors)

    def decorate(main: Main) -> Entry:
        @functools.wraps(main)
        def entry(argv: list[str] | None = None) -> int:
            main_thread = threading.current_thread() is threading.main_thread()
            previous = signal.signal(signal.SIGTERM, _terminate) if main_thread else None
            try:
                status = main(argv)
            except expected as err:
                _report(f'{prog}: error: {err}', err)
                return 1
            except KeyboardInterrupt as err:
                _report(f'{prog}: interrupted', err)
                return 130
            except Terminated as err:
                _report(f'{prog}: terminated', err)
                return 128 + signal.SIGTERM
            finally:
                if main_thread:  # None: a handler not set from Python (rclpy's), not restorable
                    signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)
            return 0 if status is None else status
        return entry
    return decorate


def _report(line: str, err: BaseException) -> None:
    """Print `line` and the notes of `err` as one line on stderr."""
    text = '; '.join([line, *getattr(err, '__notes__', ())])
    print(' '.join(part.strip() for part in text.splitlines()), file=sys.stderr)


def positive_int(text: str) -> int:
    """Argparse type: an integer >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f'must be at least 1, got {text}')
    return value


def positive(text: str) -> float:
    """Argparse type: a number > 0."""
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f'must be > 0, got {text}')
    return value
