"""Training's evaluations in a worker process while training goes on (``common/run.py``'s
schedule submits them; ``common/evaluate.py`` holds what the worker runs). The worker ignores the
terminal's signals (the training process handles them and stops it), ends when its training
process is gone, and a worker that dies costs no evaluation.
"""

import collections
import contextlib
import multiprocessing
import os
import pickle
import signal
import sys
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

import torch


def _worker_init(parent: int) -> None:
    for s in (signal.SIGINT, signal.SIGHUP):  # Ctrl-C, a closed terminal: the training process's
        signal.signal(s, signal.SIG_IGN)
    torch.set_num_threads(1)
    threading.Thread(target=_exit_with, args=(parent,), daemon=True).start()


def _call(evaluate, snapshot: bytes) -> bytes:
    """``evaluate`` on the arguments pickled in ``snapshot`` (our own, from ``submit``), its
    result pickled back the same way."""
    return pickle.dumps(evaluate(*pickle.loads(snapshot)))


def _exit_with(parent: int) -> None:
    """End this worker once its training process is gone (killed with -9, nothing told us)."""
    while os.getppid() == parent:
        time.sleep(1.0)
    os._exit(1)


@contextlib.contextmanager
def blocked_signals():
    """Ctrl-C and a closed terminal's SIGHUP blocked in this thread, and so in the processes it
    starts from their first instruction (they are the training process's to handle)."""
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGHUP})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)


class BackgroundEvaluator:
    """Evaluations that run in a worker process while training goes on (``workers=1``), or at
    once in this process (``workers=0``): the results are the same, only the wall time differs.

    ``submit(step, evaluate, *args)`` runs ``evaluate(*args)`` on a copy of ``args`` taken
    now (a snapshot of the policy at ``step``); ``finished()`` returns the evaluations that are
    done, in the order they were submitted, as ``(step, result)``; ``finished(wait=True)`` waits
    for all of them. ``evaluate`` must be a module-level function (the worker imports it). A
    worker that dies (kill -9) costs no evaluation: ``warn`` says so once, and they all run in
    this process from then on.
    """

    def __init__(self, workers: int, warn=lambda line: print(line, file=sys.stderr)):
        ctx = multiprocessing.get_context("spawn")  # no fork of a process running torch
        self.pool = None
        if workers:  # its resource tracker starts now: blind to the terminal's signals too
            with blocked_signals():
                self.pool = ProcessPoolExecutor(workers, ctx, _worker_init, (os.getpid(),))
        self.pending, self.warn = collections.deque(), warn

    def submit(self, step: int, evaluate, *args) -> None:
        # Arguments and result as bytes, by the standard pickler: torch's own (which
        # multiprocessing would use) shares tensors through a socket in TMPDIR, whose path a
        # deep TMPDIR makes too long for AF_UNIX (108 bytes).
        snapshot, future = pickle.dumps(args), None
        if self.pool is not None:  # the first submit starts the worker, signals blocked in it
            try:
                with blocked_signals():
                    future = self.pool.submit(_call, evaluate, snapshot)
            except BrokenProcessPool:
                self.lost_worker()
        if future is None:
            future = Future()
            future.set_result(_call(evaluate, snapshot))
        self.pending.append((step, future, evaluate, snapshot))

    def finished(self, wait: bool = False) -> list[tuple[int, object]]:
        done = []
        while self.pending and (wait or self.pending[0][1].done()):
            step, future, evaluate, snapshot = self.pending[0]
            try:
                result = pickle.loads(future.result())  # Ctrl-C: left pending, close() drops it
            except BrokenProcessPool:
                self.lost_worker()
                result = pickle.loads(_call(evaluate, snapshot))
            done.append((step, result))
            self.pending.popleft()
        return done

    def lost_worker(self) -> None:
        """The worker died: say so once, evaluate in this process from now on."""
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self.pool = None
            self.warn(
                "warning: the evaluation worker died; evaluations run in the training "
                "process from now on (training goes on, slower)"
            )

    def close(self, at_once: bool = False) -> None:
        """Stop the worker: ``at_once`` (an interrupted run) or with evaluations pending, end the
        one in flight now; else let it exit. Either way wait for it: a pool left winding down
        races the interpreter's exit (``OSError: [Errno 9]`` on Python 3.11)."""
        if self.pool is not None:
            if at_once or self.pending:  # concurrent.futures has no public way to stop a task
                for process in list((self.pool._processes or {}).values()):
                    process.terminate()
            self.pool.shutdown(wait=True, cancel_futures=True)
            self.pool = None
