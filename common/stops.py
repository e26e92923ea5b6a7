"""How a run ends: the signals that stop it, the exit code and the last lines of each ending.

Ctrl-C, ``kill`` and a closed terminal (``STOPS``) are held from the moment the run folder
exists (``Stops``), raised as ``KeyboardInterrupt`` once the run is under way, then ignored while
it cleans up and exits. ``ending`` gives the exit code of what ended the run (0 done; 130, 143,
129 stopped; 1 a NaN loss or a failed write) and its lines; ``say`` prints them, even into a
closed pipe.
"""

import errno
import os
import signal
from typing import NoReturn

from tqdm import tqdm

STOPS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)  # Ctrl-C, kill, a closed terminal
# write errors that stop a run in one line: a full disk, a folder made read-only
WRITE_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EACCES, errno.EPERM, errno.EROFS)


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``) or SIGHUP (a closed terminal), raised like Ctrl-C's KeyboardInterrupt
    so that a run ends cleanly; ``args[0]``: the signal."""


def raise_terminated(signum, frame) -> NoReturn:
    """The first SIGTERM or SIGHUP stops the run; later ones are ignored, so they cannot cut its
    clean-up short (kill -9 on benchmarks/run.py can send two: one per runner thread that
    dies)."""
    for s in STOPS[1:]:
        signal.signal(s, signal.SIG_IGN)
    raise Terminated(signum)


class Stops:
    """A run's stop signals, held from its creation: a signal that comes before the run is under
    way stops it as mid-run once it is (``raise_from_now``), one clean stop whenever it comes."""

    def __init__(self):
        self.held = None
        self.old_handlers = {s: signal.signal(s, self.hold) for s in STOPS}

    def hold(self, signum, frame) -> None:
        self.held = signum

    def raise_from_now(self) -> KeyboardInterrupt | None:
        """Ctrl-C and kill raise from here on; returns the error of a signal held until now."""
        signal.signal(signal.SIGINT, signal.default_int_handler)
        for s in STOPS[1:]:
            signal.signal(s, raise_terminated)
        if self.held is None:
            return None
        return KeyboardInterrupt() if self.held == signal.SIGINT else Terminated(self.held)

    def ignore(self) -> None:
        """From the clean-up on: a second Ctrl-C cannot cut it short, nor the exit after it."""
        for s in STOPS:
            signal.signal(s, signal.SIG_IGN)

    def restore(self) -> None:
        """The handlers from before the run: a bug's traceback, as usual."""
        for s, handler in self.old_handlers.items():
            signal.signal(s, handler)


def ending(error: BaseException | None, step: int, run_dir: str) -> tuple[int | None, list[str]]:
    """The exit code of a run ended by ``error`` (None: it finished) and the lines that say so:
    Ctrl-C, kill or a closed terminal exit 130, 143 or 129, logs kept; a NaN loss, a full disk or
    a folder turned read-only exit 1 in one error line. Anything else is a bug: None, no line
    (its traceback follows)."""
    if error is None:
        return 0, []
    if isinstance(error, KeyboardInterrupt):
        signum = error.args[0] if isinstance(error, Terminated) else signal.SIGINT
        return 128 + signum, [f"interrupted at step {step:,}; logs are kept in {run_dir}"]
    if isinstance(error, FloatingPointError):
        return 1, [f"error: {error}"]
    if isinstance(error, OSError) and error.errno in WRITE_ERRORS:
        return 1, [f"error: {disk_error(error, run_dir)}"]
    return None, []


def disk_error(error: Exception, run_dir: str) -> str:
    """One line for a failed write: which file, and why (the disk is full, ...)."""
    if not isinstance(error, OSError):
        return str(error)
    name = error.filename or f"a file in {run_dir}"
    full = " (the disk is full)" if error.errno in (errno.ENOSPC, errno.EDQUOT) else ""
    return f"could not write {name}: {error.strerror or error}{full}"


def say(message: str, file, progress=None) -> None:
    """Print a line (above the live bar if one is drawn); a closed pipe (Ctrl-C on
    ``... | tee log`` ends ``tee`` too) sends the rest of the output to /dev/null instead of
    stopping the clean-up."""
    try:
        if progress is not None and not progress.disable:
            tqdm.write(message, file=file)
        else:
            print(message, file=file, flush=True)
    except OSError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), file.fileno())
