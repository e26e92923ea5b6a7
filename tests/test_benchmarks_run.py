"""benchmarks/run.py: Ctrl-C or SIGTERM stops the suite (the running scripts save, nothing queued
starts, the same command resumes), kill -9 takes the running scripts with it, two runners on one
suite run each run once, and bad input (a folder it cannot write in, an --only that matches no
run, --workers below 1, --backend ray without Ray) is one error line before any run."""

import contextlib
import fcntl
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ROOT, assert_clean_error, read_only

from benchmarks import run

CHILD = '''"""A script as run.py sees one: Ctrl-C or SIGTERM saves a resume point and exits
128 + signal (the one named "stubborn" ignores both); with --resume it is done at once."""
import os, signal, sys, time
from pathlib import Path

argv = sys.argv
log_dir, name = Path(argv[argv.index("--log-dir") + 1]), argv[argv.index("--exp-name") + 1]
if "--resume" in argv:
    (log_dir / "resumed").touch()
    sys.exit(0)


def stop(signum, frame):
    for s in (signal.SIGINT, signal.SIGTERM):  # as the real scripts: a second signal is ignored
        signal.signal(s, signal.SIG_IGN)
    with open(log_dir / "signals", "a") as f:
        f.write(f"{signum}\\n")
    time.sleep(float(os.environ.get("FAKE_SAVE", "0.5")))  # saving
    (log_dir / "attempt").mkdir(exist_ok=True)
    (log_dir / "attempt" / "resume.pt").touch()
    sys.exit(128 + signum)


for signum in (signal.SIGINT, signal.SIGTERM):
    signal.signal(signum, signal.SIG_IGN if name == "stubborn" else stop)
with open(log_dir / "starts", "a") as f:
    f.write(f"{os.getpid()}\\n")
time.sleep(float(os.environ.get("FAKE_SLEEP", "30")))
'''
DRIVER = """import sys
sys.path.insert(0, {root!r})
from benchmarks import run
run.STOP_TIMEOUT = 2
names = ("clean", "stubborn", "queued1", "queued2")
run.suite_runs = lambda *args: [run.Run(name, {child!r}, "Env-v0", 1) for name in names]
sys.exit(run.cli())
"""


def runner(tmp_path: Path, *flags: str, **env: str) -> subprocess.Popen:
    """benchmarks/run.py's command line on a suite of fake scripts, in a process group of its own
    (the test ends whatever is left of it)."""
    (tmp_path / "child.py").write_text(CHILD)
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER.format(root=str(ROOT), child=str(tmp_path / "child.py")))
    cmd = [sys.executable, str(driver), "--suite", "quick", "--out-dir", str(tmp_path), *flags]
    return subprocess.Popen(
        cmd,
        cwd=ROOT,
        env={**os.environ, **env},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )


def folder(tmp_path: Path, name: str) -> Path:
    return tmp_path / "quick" / f"{name}__Env-v0__seed1"


def wait_for(condition, timeout: float = 10) -> None:
    end = time.time() + timeout
    while not condition():
        assert time.time() < end, "timed out"
        time.sleep(0.05)


def alive(pid: int) -> bool:
    """Running, not a zombie (whose command line is empty)."""
    try:
        return bool(Path(f"/proc/{pid}/cmdline").read_bytes())
    except OSError:
        return False


def end(proc: subprocess.Popen, tmp_path: Path) -> None:
    """Kill what a failed test left running: the runner's group and the fake scripts."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
    for starts in (tmp_path / "quick").glob("*/starts"):
        for pid in map(int, starts.read_text().split()):
            if alive(pid):
                os.kill(pid, signal.SIGKILL)


@pytest.mark.skipif(sys.platform != "linux", reason="reads /proc")
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_the_suite_and_the_same_command_resumes_it(tmp_path, signum):
    """Two runs at once: the clean one gets the signal once, saves and exits 128 + signal; the
    stubborn one is killed after run.STOP_TIMEOUT (2 s here); the queued ones never start. One
    line says so and how to resume, the exit code is the signal's, no traceback. The same
    command then resumes the clean run, starts the stubborn one again and runs the others."""
    proc = runner(tmp_path, "--workers", "2")
    try:
        wait_for(lambda: all((folder(tmp_path, n) / "starts").exists() for n in ("clean", "stubborn")))
        os.kill(proc.pid, signum)
        out, err = proc.communicate(timeout=15)
    finally:
        end(proc, tmp_path)
    assert proc.returncode == 128 + signum and "Traceback" not in err, err
    header, line = out.splitlines()  # one line after the suite's first
    counts = "0 finished, 0 failed, 2 interrupted (1 with a resume point), 2 not started; "
    assert line.startswith(f"stopped by {signal.Signals(signum).name}: {counts}"), line
    assert "--suite quick" in line and "resume" in line, line
    assert (folder(tmp_path, "clean") / "signals").read_text() == f"{signum}\n"
    assert (folder(tmp_path, "clean") / "exit_code").read_text() == f"{128 + signum}\n"
    assert (folder(tmp_path, "stubborn") / "exit_code").read_text() == "-9\n"
    assert not folder(tmp_path, "queued1").exists() and not folder(tmp_path, "queued2").exists()

    proc = runner(tmp_path, "--workers", "2", FAKE_SLEEP="0")
    try:
        out, err = proc.communicate(timeout=15)
    finally:
        end(proc, tmp_path)
    assert proc.returncode == 0, out + err
    assert "4 to run, 0 already finished" in out
    assert (folder(tmp_path, "clean") / "resumed").exists()
    assert len((folder(tmp_path, "stubborn") / "starts").read_text().split()) == 2
    assert all((folder(tmp_path, n) / "exit_code").read_text() == "0\n" for n in ("clean", "stubborn", "queued1", "queued2"))


@pytest.mark.skipif(sys.platform != "linux", reason="PR_SET_PDEATHSIG is Linux's")
def test_kill_9_takes_the_runs_with_it_and_a_rerun_leaves_a_live_one_alone(tmp_path):
    """kill -9 on the runner: its running script gets SIGTERM and saves (8 s here); a rerun while
    it saves starts no second copy beside it, and says so; once it is gone a rerun resumes it."""
    proc = runner(tmp_path, "--only", "clean", FAKE_SAVE="8")
    run_dir = folder(tmp_path, "clean")
    try:
        wait_for(lambda: (run_dir / "starts").exists())
        (pid,) = map(int, (run_dir / "starts").read_text().split())
        os.kill(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=10)
        wait_for(lambda: (run_dir / "signals").exists(), timeout=5)
        # SIGTERM, not SIGKILL; maybe twice: the kernel sends the death signal each time the
        # script passes from a dying thread of the runner to another
        assert set((run_dir / "signals").read_text().split()) == {str(signal.SIGTERM)}
        rerun = runner(tmp_path, "--only", "clean")
        out, err = rerun.communicate(timeout=15)
        assert alive(pid), "the rerun came after the script's clean stop: make FAKE_SAVE longer"
        assert rerun.returncode == 1 and "Traceback" not in err, out + err
        assert f"clean__Env-v0__seed1: still running as pid {pid}" in out, out
        assert "0 to run" in out and len((run_dir / "starts").read_text().split()) == 1
        wait_for(lambda: not alive(pid))
        rerun = runner(tmp_path, "--only", "clean")
        out, err = rerun.communicate(timeout=15)
        assert rerun.returncode == 0, out + err
        assert (run_dir / "resumed").exists() and (run_dir / "exit_code").read_text() == "0\n"
    finally:
        end(proc, tmp_path)


def run_py(*flags: str, **env: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "benchmarks/run.py", "--suite", "quick", *flags]
    env = {**os.environ, **env}
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("kind", ["file", "read-only folder"])
def test_an_out_dir_it_cannot_write_in_is_one_error_line(tmp_path, kind):
    """--out-dir a file or a read-only folder: one line naming it, before any run starts (no
    traceback from each worker thread)."""
    out_dir = tmp_path / "out"
    if kind == "file":
        out_dir.write_text("")
    else:
        out_dir.mkdir()
    with read_only(out_dir) if kind == "read-only folder" else contextlib.nullcontext():
        result = run_py("--out-dir", str(out_dir), "--only", "FetchReach")
    assert_clean_error(result, f"--out-dir {out_dir}", "cannot write")
    assert "to run" not in result.stdout


def test_an_only_that_matches_no_run_is_an_error_with_a_hint(tmp_path):
    """--only ipg_herr (a typo) does not run nothing and exit 0: one line names the closest run
    names; with nothing close, it lists them."""
    result = run_py("--out-dir", str(tmp_path), "--only", "ipg_herr")
    assert_clean_error(result, "--only ipg_herr", "did you mean ipg_her?")
    result = run_py("--out-dir", str(tmp_path), "--only", "xyzzy", "--dry-run")
    assert_clean_error(result, "--only xyzzy", "FetchReach-v4", "ppo_kl")
    assert not (tmp_path / "quick").exists()


def test_a_run_another_runner_finished_meanwhile_is_not_started_again(tmp_path):
    """Two runners on one suite: the first lists a run, the second finishes it, and when the
    first comes to it, it is done: not started again over the finished run's folder."""
    marker = tmp_path / "started"
    command = [sys.executable, "-c", f"open({str(marker)!r}, 'w').close()"]
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "exit_code").write_text("0\n")
    assert run.execute(command, str(tmp_path / "run")) == 0
    assert not marker.exists() and (tmp_path / "run" / "exit_code").read_text() == "0\n"
    assert run.execute(command, str(tmp_path / "other")) == 0 and marker.exists()


def test_two_runners_on_one_suite_run_each_run_once(tmp_path):
    """A second runner started while the first's run is running: each run starts once, in one
    runner or the other (a run the other runner holds is left to it and named), both end without
    a traceback, and every run's exit code is 0."""
    first = runner(tmp_path, "--workers", "1", FAKE_SLEEP="3")
    second = None
    try:
        wait_for(lambda: (folder(tmp_path, "clean") / "starts").exists())
        second = runner(tmp_path, "--workers", "1", FAKE_SLEEP="3")
        results = [proc.communicate(timeout=60) for proc in (first, second)]
    finally:
        for proc in (first, second or first):
            end(proc, tmp_path)
    for out, err in results:
        assert "Traceback" not in err, err
    names = ("clean", "stubborn", "queued1", "queued2")
    assert all(len((folder(tmp_path, n) / "starts").read_text().split()) == 1 for n in names)
    assert all((folder(tmp_path, n) / "exit_code").read_text() == "0\n" for n in names)
    assert "not started again" in results[0][0] + results[1][0]


def test_a_run_another_runner_holds_is_not_started(tmp_path):
    """While another runner holds a run's lock, execute starts nothing there and writes no exit
    code: it returns None (not started)."""
    marker = tmp_path / "started"
    command = [sys.executable, "-c", f"open({str(marker)!r}, 'w').close()"]
    (tmp_path / "run").mkdir()
    with open(tmp_path / "run" / "run.lock", "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)  # as the other runner holds it
        assert run.execute(command, str(tmp_path / "run")) is None
    assert not marker.exists() and not (tmp_path / "run" / "exit_code").exists()
    assert run.execute(command, str(tmp_path / "run")) == 0 and marker.exists()


@pytest.mark.parametrize("workers", ["-1", "0"])
def test_workers_below_one_is_one_error_line(tmp_path, workers):
    """--workers -1 ran one worker under a header saying -1: refused, nothing written."""
    result = run_py("--out-dir", str(tmp_path), "--workers", workers)
    assert_clean_error(result, f"--workers {workers}", "at least 1")
    assert "to run" not in result.stdout and not (tmp_path / "quick").exists()


def test_backend_ray_without_ray_is_one_error_line(tmp_path):
    """--backend ray where Ray does not import (a fake ray on PYTHONPATH raises ImportError): one
    line naming the install of requirements-test.txt's pinned Ray, and no suite folder."""
    fake = tmp_path / "fake"
    fake.mkdir()
    (fake / "ray.py").write_text("raise ImportError('no Ray here')\n")
    pins = (ROOT / "requirements-test.txt").read_text().split()
    pin = next(word for word in pins if word.startswith("ray=="))
    out_dir = tmp_path / "runs"
    result = run_py("--out-dir", str(out_dir), "--backend", "ray", PYTHONPATH=str(fake))
    assert not out_dir.exists(), "a suite folder was written before Ray was found missing"
    assert_clean_error(result, "--backend ray", f"pip install {pin}")
    assert "to run" not in result.stdout
