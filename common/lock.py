"""The run folder's lock: one process at a time runs in a run folder."""

import fcntl
import os

from common import cli


def lock(run_dir: str):
    """Hold ``run_dir/run.lock`` (with this pid) while the run lives: a second run of the same
    folder (two ``--resume`` at once) is refused. The kernel frees it when the process dies."""
    path = os.path.join(run_dir, "run.lock")
    try:
        handle = open(path, "a+")
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        cli.fail(f"{run_dir} is in use by a running process (pid {handle.read().strip() or '?'})")
    except OSError as e:
        cli.fail(f"cannot write in {run_dir}: {e.strerror}")
    handle.truncate(0)
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    return handle
