"""Run a grid of script x task x seed, each run its own process, locally or on a Ray cluster.

    python benchmarks/run.py --suite paper            # Figures 3-5 of the paper, 5 seeds
    python benchmarks/run.py --suite quick --dry-run  # print the commands only
    python benchmarks/report.py --suite paper         # figures and table from the event files

Every run gets a folder ``{out-dir}/{suite}/{name}__{env_id}__seed{seed}/`` holding the script's
own run folder (TensorBoard events), ``stdout.log``, ``stderr.log``, ``exit_code``, ``run.lock``
(held by the runner from before the run starts until its exit code is written: a second runner on
the suite starts no run the first holds) and while it runs ``pid`` (a later call starts no second
copy of a run still running). A run whose ``exit_code`` says 0 is skipped by the next call
(resume); a failed one is run again, and one stopped goes on from its resume point if it has one.
The call exits non-zero if any run failed or was left to another runner.
Ctrl-C (or SIGTERM) stops the suite: the running scripts save and exit, no other run starts.

The suites, what each runs and how report.py shows it: ``SUITES`` in ``benchmarks/suites.py``.
"""

import ctypes
import difflib
import fcntl
import importlib
import os
import shlex
import signal
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.suites import ROOT, Run, suite_runs  # noqa: E402  what each suite runs

RAY = "ray==2.60.0"  # requirements-test.txt's pin, the Ray the ray backend is tested with
WANDB = "wandb==0.31.0"  # --track's, as requirements-test.txt pins it


@dataclass
class Args:
    """Run a suite of script x task x seed, one process each; a later call resumes it."""

    suite: Literal[
        "paper",
        "ablations",
        "eta",
        "mixing",
        "push",
        "fetch",
        "hopper",
        "goals",
        "one_recipe",
        "one_set",
        "every_goal",
        "quick",
    ]
    """which grid (benchmarks/suites.py's docstring): quick takes seconds, paper hours"""
    seeds: tuple[int, ...] = ()
    """override the suite's seeds"""
    only: str = ""
    """run only the runs whose folder name contains this text"""
    workers: int = os.cpu_count() or 1
    """runs at once (each uses one core)"""
    out_dir: str = "benchmarks/runs"
    """parent of the suite folders"""
    backend: Literal["local", "ray"] = "local"
    """local processes, or one Ray task per run (needs Ray; a multi-node cluster: shared files)"""
    ray_address: str | None = None
    """address of an existing Ray cluster (None: start a local Ray instance)"""
    dry_run: bool = False
    """print the commands and exit"""
    push_steps: int = 1_500_000
    """the push suite's budget per run (in its runs' names; resumable every 50,000 steps)"""
    track: bool = False
    """pass --track to every run (Weights & Biases), the suite as the W&B group"""


STOPPED, RUNNING, LOCK = [], set(), threading.RLock()  # the signals received, the children
STOP_TIMEOUT = 60.0  # seconds a stopped child has to save and exit before it is killed
LIBC = ctypes.CDLL(None) if sys.platform == "linux" else None


def die_with_runner() -> None:
    """In a child before it starts (Linux): SIGTERM when the runner ends, even by kill -9, so
    that the run stops as on Ctrl-C (saving) rather than going on as an orphan."""
    LIBC.prctl(1, signal.SIGTERM)  # 1: PR_SET_PDEATHSIG


def stop(signum, frame) -> None:
    """Ctrl-C or SIGTERM: no run starts any more, and each running one gets the signal once (its
    own process group keeps the terminal's Ctrl-C from it): its script saves and exits (130 or
    143). A script still running ``STOP_TIMEOUT`` s later, or at a second signal, is killed."""
    with LOCK:
        STOPPED.append(signum)
        for proc in RUNNING:
            proc.send_signal(signum if len(STOPPED) == 1 else signal.SIGKILL)
    if len(STOPPED) == 1:
        timer = threading.Timer(STOP_TIMEOUT, stop, (signal.SIGKILL, None))
        timer.daemon = True  # the runner does not wait for it to end
        timer.start()


def execute(command: list[str], run_dir: str) -> int | None:
    """Run one command with its output kept in ``run_dir``; write and return its exit code (None:
    not started, the suite was stopped or another runner holds the run). While it runs, its pid is
    in ``run_dir/pid``. The runner holds ``run_dir/run.lock`` from before the run starts until its
    exit code is written, so that two runners on one suite never run it at once; a run another
    runner finished since this one listed it is not started again: 0."""
    run_dir = Path(run_dir)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with LOCK:
        if STOPPED:  # a queued run gets no folder
            return None
        run_dir.mkdir(parents=True, exist_ok=True)
    with open(run_dir / "run.lock", "a") as run_lock:  # the kernel frees it if the runner dies
        try:
            fcntl.flock(run_lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:  # another runner runs it
            return None
        if running(run_dir):  # a killed runner's run, still saving
            return None
        if finished(run_dir):
            return 0
        with LOCK:  # a stop comes either before (nothing starts) or after (it finds the child)
            if STOPPED:
                return None
            # appended: an attempt that resumes keeps the output of the one it resumes
            with open(run_dir / "stdout.log", "a") as out, open(run_dir / "stderr.log", "a") as err:
                proc = subprocess.Popen(
                    command,
                    cwd=ROOT,
                    env=env,
                    stdout=out,
                    stderr=err,
                    start_new_session=True,
                    preexec_fn=die_with_runner if LIBC else None,
                )
            RUNNING.add(proc)
            (run_dir / "pid").write_text(f"{proc.pid}\n")
        code = proc.wait()
        with LOCK:
            RUNNING.discard(proc)
        (run_dir / "exit_code").write_text(f"{code}\n")
        (run_dir / "pid").unlink()
    return code


def finished(run_dir: Path) -> bool:
    return (run_dir / "exit_code").exists() and (run_dir / "exit_code").read_text().strip() == "0"


def running(run_dir: Path) -> int | None:
    """The pid of a process still running this run (its runner was killed), or None: the pid
    file names no live process, or (on Linux) one whose command line does not name the run (a
    zombie, or the pid taken by another process since)."""
    try:
        pid = int((run_dir / "pid").read_text())
        os.kill(pid, 0)
        cmdline = Path(f"/proc/{pid}/cmdline")
        return None if cmdline.exists() and run_dir.name not in cmdline.read_text() else pid
    except (OSError, ValueError):
        return None


def fmt(seconds: float) -> str:
    return time.strftime("%H:%M:%S", time.gmtime(seconds))


def refuse(message: str) -> int:
    """Bad input: one line on stderr, exit code 2, no run started."""
    print(f"error: {message}", file=sys.stderr)
    return 2


def main(args: Args) -> int:
    suite_dir = Path(args.out_dir) / args.suite
    every = suite_runs(args.suite, args.seeds, args.push_steps)
    runs = [r for r in every if args.only in r.folder]
    if not runs:  # a typo would otherwise run nothing and say all is well
        names = sorted({r.name for r in every} | {r.env_id for r in every})
        close = difflib.get_close_matches(args.only, names, n=3)
        hint = f"did you mean {' or '.join(close)}?" if close else f"try one of {', '.join(names)}"
        return refuse(
            f"--only {args.only}: no run of the {args.suite} suite has it in its "
            f"folder name ({{name}}__{{env_id}}__seed{{seed}}); {hint}"
        )
    if args.workers < 1:
        return refuse(f"--workers {args.workers}: the runs at once must be at least 1")
    if args.backend == "ray":
        try:
            import ray
        except ImportError:
            return refuse(f"--backend ray needs Ray: pip install {RAY}")
    if args.track:
        try:
            import wandb  # noqa: F401
        except ImportError:
            return refuse(f"--track needs wandb: pip install {WANDB}")
        os.environ["WANDB_RUN_GROUP"] = args.suite  # every run's W&B group
    if not args.dry_run:  # a folder the runs cannot write in fails here, not in each worker
        try:
            suite_dir.mkdir(parents=True, exist_ok=True)
            tempfile.TemporaryFile(dir=suite_dir).close()
        except OSError as error:
            return refuse(
                f"--out-dir {args.out_dir}: cannot write in {suite_dir} "
                f"({error.strerror}); name a folder the runs can write in"
            )
    todo = [r for r in runs if not finished(suite_dir / r.folder)]
    skipped = len(runs) - len(todo)
    alive = {r: pid for r in todo if (pid := running(suite_dir / r.folder))}
    for r, pid in alive.items():  # another runner's run, or a killed one's: no second copy
        print(f"{r.folder}: still running as pid {pid}; not started again", flush=True)
    todo = [r for r in todo if r not in alive]
    held = []  # the runs another runner took since they were listed
    if args.dry_run:
        try:
            for r in todo:
                print(" ".join(r.command(suite_dir / r.folder, args.track)))
            print(f"{len(todo)} to run, {skipped} already finished")
            sys.stdout.flush()
        except BrokenPipeError:  # `--dry-run | head`: the reader has what it wanted
            sys.stdout = open(os.devnull, "w")
        return 0
    start, failed, stopped, done = time.time(), [], [], 0
    print(
        f"suite {args.suite}: {len(todo)} to run, {skipped} already finished, {args.workers} workers, backend {args.backend}",
        flush=True,
    )

    def report(run: Run, code: int | None) -> None:
        nonlocal done
        if STOPPED and code != 0:  # stopped by the signal, or never started (None)
            if code is not None:
                stopped.append(run.folder)
            return
        if code is None:  # not started: another runner holds it
            print(f"{run.folder}: run by another runner; not started again", flush=True)
            held.append(run)
            return
        done += 1
        elapsed = time.time() - start
        eta = elapsed / done * (len(todo) - done - len(held))
        status = "ok" if code == 0 else f"FAILED (exit {code}; see {suite_dir / run.folder / 'stderr.log'})"
        print(
            f"[{done}/{len(todo)}] {run.folder}: {status}  elapsed {fmt(elapsed)}  ETA {fmt(eta)}",
            flush=True,
        )
        if code != 0:
            failed.append(run.folder)

    if args.backend == "ray":
        # workers import this module from the project folder (the same path on every node)
        group = {"WANDB_RUN_GROUP": args.suite} if args.track else {}
        ray.init(
            address=args.ray_address,
            include_dashboard=False,
            log_to_driver=False,
            runtime_env={"env_vars": {"PYTHONPATH": str(ROOT), **group}},
        )
        # this module by name (ROOT is on sys.path), as run.py's __main__ won't pickle
        remote = ray.remote(num_cpus=1)(importlib.import_module("benchmarks.run").execute)
        pending = {remote.remote(r.command(suite_dir / r.folder, args.track), str(suite_dir / r.folder)): r for r in todo}
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                report(pending.pop(ref), ray.get(ref))
        ray.shutdown()
    else:
        with ThreadPoolExecutor(max_workers=args.workers) as pool:
            futures = {
                pool.submit(execute, r.command(suite_dir / r.folder, args.track), str(suite_dir / r.folder)): r for r in todo
            }
            for future in as_completed(futures):
                report(futures[future], future.result())
    if STOPPED:
        resumable = sum(any((suite_dir / f).glob("*/resume.pt")) for f in stopped)
        print(
            f"stopped by {signal.Signals(STOPPED[0]).name}: {done - len(failed)} finished, "
            f"{len(failed)} failed, {len(stopped)} interrupted ({resumable} with a resume "
            f"point), {len(todo) - done - len(stopped)} not started; to resume, run the same "
            f"command again: python {shlex.join(sys.argv)}",
            flush=True,
        )
        return 128 + STOPPED[0]
    print(
        f"summary: {done - len(failed)} done, {len(failed)} failed, {skipped} skipped, "
        f"{len(alive) + len(held)} still running elsewhere, "
        f"wall time {fmt(time.time() - start)}"
    )
    for name in failed:
        print(f"failed: {name}")
    return 1 if failed or alive or held else 0


def cli() -> int:
    """The command line; Ctrl-C and SIGTERM stop a local suite cleanly (``stop``)."""
    args = tyro.cli(Args)
    if args.backend == "local":
        signal.signal(signal.SIGINT, stop)
        signal.signal(signal.SIGTERM, stop)
    return main(args)


if __name__ == "__main__":
    sys.exit(cli())
