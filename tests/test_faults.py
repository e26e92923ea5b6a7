"""Nothing lost, nothing silent: whatever stops a run (a NaN, Ctrl-C or kill at any moment, a
pipe closed under it, kill -9, a full disk, a second run of its folder, a broken checkpoint), its
last good checkpoint survives, its last line names it, no process outlives it, and bad input is
one ``error:`` line with nothing written."""

import errno
import fcntl
import os
import resource
import runpy
import shutil
import signal
import subprocess
import sys
import time

import pytest
import torch
from conftest import ROOT, alive, assert_clean_error, children, run_dirs, run_script, scalars

from common import checkpoint, evaluate, stops

TINY = ("--env-id", "FetchReach-v4", "--total-timesteps", "200", "--eval-freq", "0", "--eval-episodes", "2")
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
LONG_REACH = "--env-id FetchReach-v4 --total-timesteps 1000000 --eval-freq 200 --eval-episodes 2 --save-model".split()
TINY_PPO = "--num-envs 2 --num-steps 64 --total-timesteps 1024 --num-minibatches 2 --update-epochs 1 --eval-freq 0".split()
TINY_PPO += ["--eval-workers", "0"]  # eight updates of 128 steps, no evaluation before the end


def start(log_dir, *flags, **popen):
    """``ipg_her.py`` in the background, its output piped; waits for its ``run folder:`` line."""
    cmd = [sys.executable, str(ROOT / "ipg_her.py"), "--log-dir", str(log_dir), *flags]
    popen = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True, "env": ENV} | popen
    proc = subprocess.Popen(cmd, cwd=ROOT, **popen)
    first = proc.stdout.readline()
    assert first.startswith("run folder: "), first + proc.communicate()[1]
    return proc, first.removeprefix("run folder: ").strip()


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A tiny finished run with a model.pt and a resume.pt."""
    log_dir = tmp_path_factory.mktemp("finished")
    result = run_script("ipg_her.py", log_dir, *TINY, "--save-model", "--resume-freq", "100")
    assert result.returncode == 0, result.stderr
    return run_dirs(log_dir)[0]


def test_a_nan_stop_keeps_the_good_model_and_evaluate_refuses_a_nan_one(monkeypatch, tmp_path, capsys):
    """A NaN injected into the weights at the third update: the model.pt saved at step 256
    stays as it was, the run exits 1 with one error line, its last line names that model; a
    model holding NaN is refused by ``common.evaluate`` with one line."""
    steps, original = [0], torch.optim.Adam.step

    def poisoned(self, *args, **kwargs):
        out = original(self, *args, **kwargs)
        steps[0] += 1
        if steps[0] == 5:  # iterations 1-2 take two Adam steps each
            for group in self.param_groups:
                for p in group["params"]:
                    p.data.fill_(float("nan"))
        return out

    argv = [
        "ppo_kl.py",
        "--log-dir",
        str(tmp_path),
        *TINY_PPO,
        "--save-model",
        "--save-freq",
        "256",
    ]
    monkeypatch.setattr(torch.optim.Adam, "step", poisoned)
    monkeypatch.setattr(sys, "argv", argv)
    saved = {}
    real_save = checkpoint.save

    def recording_save(path, *args, **kwargs):
        real_save(path, *args, **kwargs)
        saved.setdefault(path, open(path, "rb").read())  # the first, good one

    monkeypatch.setattr(checkpoint, "save", recording_save)
    with pytest.raises(SystemExit) as stop:
        runpy.run_path(str(ROOT / "ppo_kl.py"), run_name="__main__")
    assert stop.value.code == 1
    (path,) = saved
    assert open(path, "rb").read() == saved[path], "the good model.pt was overwritten"
    assert checkpoint.load(path)["agent"]  # finite, loads

    bad = torch.load(path, weights_only=True)
    bad["agent"]["actor_logstd"].fill_(float("nan"))
    torch.save(bad, tmp_path / "nan.pt")
    with pytest.raises(SystemExit) as refused:
        evaluate.main([str(tmp_path / "nan.pt"), "--seed", "1", "--episodes", "1"])
    assert refused.value.code == 2
    assert "NaN or infinite values (agent.actor_logstd)" in capsys.readouterr().err


def test_the_last_line_of_a_nan_stop_names_the_good_model(tmp_path):
    """The same stop seen from outside: one error line, the last line names model.pt's step."""
    result = run_script(
        "qprop_ppo.py",
        tmp_path,
        "--env-id",
        "Hopper-v5",
        "--critic-learning-rate",
        "1e8",
        "--num-steps",
        "128",
        "--save-model",
        "--save-freq",
        "512",
        "--resume-freq",
        "512",
        "--total-timesteps",
        "20480",
        "--eval-freq",
        "0",
    )
    assert result.returncode == 1, result.stdout + result.stderr
    assert_clean_error(result, "NaN or infinite")
    last = result.stdout.strip().splitlines()[-1]
    assert last.startswith("stopped: ") and "model.pt of step " in last, last
    (run_dir,) = run_dirs(tmp_path)
    content = checkpoint.load(str(run_dir / "model.pt"))
    assert not checkpoint.not_finite(content["agent"])


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_right_after_the_run_folder_is_a_clean_stop(tmp_path, sig, code):
    proc, run_dir = start(tmp_path, *TINY)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err
    assert "Traceback" not in err and err.startswith("interrupted at step 0"), err
    assert out.strip().splitlines()[-1].startswith("stopped: 0 steps"), out


def test_a_second_sigterm_cannot_cut_the_clean_up_short():
    """kill -9 on benchmarks/run.py can send its running script SIGTERM twice."""
    before = signal.signal(signal.SIGTERM, stops.raise_terminated)
    try:
        with pytest.raises(stops.Terminated):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)  # the handler runs here
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_IGN
        os.kill(os.getpid(), signal.SIGTERM)  # the clean-up goes on
    finally:
        signal.signal(signal.SIGTERM, before)


def test_kill_9_leaves_no_process_behind(tmp_path):
    """The evaluation worker (and what multiprocessing started beside it) ends with its run,
    even in the middle of a long evaluation (30,000 episodes: minutes)."""
    proc, _ = start(
        tmp_path, "--env-id", "FetchReach-v4", "--total-timesteps", "1000000", "--eval-freq", "100", "--eval-episodes", "30000"
    )
    deadline = time.time() + 60
    while not (kids := children(proc.pid)) and time.time() < deadline:
        time.sleep(0.5)
    assert kids, "no evaluation worker started"
    time.sleep(10)  # the worker has imported torch and is evaluating step 100
    kids = children(proc.pid)
    proc.kill()
    proc.wait()
    deadline = time.time() + 15
    while any(alive(k) for k in kids) and time.time() < deadline:
        time.sleep(0.5)
    left = [k for k in kids if alive(k)]
    for k in left:
        os.kill(k, signal.SIGKILL)
    assert not left, f"{len(left)} process(es) outlived their run"


def test_a_pipe_closed_by_ctrl_c_costs_no_checkpoint(tmp_path):
    """``... --save-model 2>&1 | tee log`` and Ctrl-C: tee dies too, the run's output goes
    nowhere, yet the model is saved and the exit code is Ctrl-C's."""
    proc, run_dir = start(
        tmp_path,
        "--env-id",
        "FetchReach-v4",
        "--total-timesteps",
        "1000000",
        "--eval-freq",
        "200",
        "--save-model",
        stderr=subprocess.STDOUT,
    )
    while "evaluation of step" not in proc.stdout.readline():
        pass
    proc.stdout.close()  # tee is gone
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=60) == 130
    assert checkpoint.load(os.path.join(run_dir, "model.pt"))["agent"]


def test_a_signal_during_the_last_evaluation_stops_at_once(tmp_path):
    """The final evaluation (30,000 episodes: minutes) is dropped, not waited for."""
    proc, _ = start(
        tmp_path, "--env-id", "FetchReach-v4", "--total-timesteps", "200", "--eval-freq", "0", "--eval-episodes", "30000"
    )
    time.sleep(15)  # training's 200 steps are done; the evaluation of 1.5M steps is not
    assert proc.poll() is None
    sent = time.time()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 143 and "Traceback" not in err, err
    # saving takes seconds on a loaded machine (CI runs the tests two at a time); waiting for the
    # evaluation would take minutes
    assert time.time() - sent < 20, f"took {time.time() - sent:.0f} s to stop"


def test_a_second_run_of_a_folder_in_use_is_refused(finished_run):
    with open(finished_run / "run.lock", "a+") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)  # as a live run holds it
        before = sorted(os.listdir(finished_run))
        result = run_script(
            "ipg_her.py", finished_run.parent, *TINY, "--save-model", "--resume-freq", "100", "--resume", str(finished_run)
        )
    assert_clean_error(result, "is in use by a running process")
    assert sorted(os.listdir(finished_run)) == before


@pytest.mark.parametrize("damage", ["a model.pt", "no rng", "truncated"])
def test_a_broken_resume_file_is_one_line_and_writes_nothing(finished_run, tmp_path, damage):
    run_dir = tmp_path / "run"
    shutil.copytree(finished_run, run_dir)
    resume = run_dir / "resume.pt"
    if damage == "a model.pt":
        shutil.copy(run_dir / "model.pt", resume)
    elif damage == "no rng":
        content = torch.load(resume, weights_only=True)
        del content["rng"]
        torch.save(content, resume)
    else:
        os.truncate(resume, 1000)
    before = sorted(os.listdir(run_dir))
    result = run_script("ipg_her.py", tmp_path, *TINY, "--save-model", "--resume-freq", "100", "--resume", str(run_dir))
    needle = {
        "a model.pt": "a model.pt, not a resume point",
        "no rng": "lacks rng",
        "truncated": "is truncated or corrupt (1,000 bytes)",
    }[damage]
    assert_clean_error(result, str(resume), needle)
    assert sorted(os.listdir(run_dir)) == before


def test_a_failed_write_keeps_the_old_file_and_removes_its_temporary(monkeypatch, tmp_path):
    path = tmp_path / "resume.pt"
    checkpoint._write({"format_version": checkpoint.FORMAT_VERSION, "x": 1}, str(path))
    real_open = open

    def full_disk(name, mode="r", *args, **kwargs):
        f = real_open(name, mode, *args, **kwargs)
        if "w" in mode:
            f.close()
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return f

    monkeypatch.setattr("builtins.open", full_disk)
    with pytest.raises(OSError) as failed:
        checkpoint._write({"format_version": checkpoint.FORMAT_VERSION, "x": 2}, str(path))
    monkeypatch.undo()
    assert failed.value.errno == errno.ENOSPC and failed.value.filename == str(path)
    assert os.listdir(tmp_path) == ["resume.pt"]
    assert checkpoint._read(str(path))["x"] == 1
    from common.stops import disk_error

    assert disk_error(failed.value, str(tmp_path)).endswith("(the disk is full)")


def test_a_run_out_of_disk_stops_in_one_line_and_keeps_its_resume_point(tmp_path):
    """Files capped at 400 kB (RLIMIT_FSIZE: writes beyond fail as on a full disk): the replay
    buffer outgrows it, the resume point that no longer fits fails, the one before stays."""
    limit = 400_000

    def cap():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    result = subprocess.run(
        [
            sys.executable,
            str(ROOT / "ipg_her.py"),
            "--log-dir",
            str(tmp_path),
            "--env-id",
            "FetchReach-v4",
            "--total-timesteps",
            "30000",
            "--eval-freq",
            "0",
            "--eval-episodes",
            "2",
            "--resume-freq",
            "500",
        ],
        cwd=ROOT,
        env=ENV,
        capture_output=True,
        text=True,
        preexec_fn=cap,
        timeout=300,
    )
    assert result.returncode == 1, result.stdout + result.stderr
    assert_clean_error(result, "could not write", "resume.pt")
    (run_dir,) = run_dirs(tmp_path)
    assert not [f for f in os.listdir(run_dir) if f.endswith(".tmp")]
    last = result.stdout.strip().splitlines()[-1]
    step = int(last.split("goes on from step ")[1].replace(",", ""))
    assert checkpoint._read(str(run_dir / "resume.pt"))["global_step"] == step


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_an_interrupted_evaluation_is_one_line(finished_run, sig, code):
    cmd = [sys.executable, "-m", "common.evaluate", str(finished_run), "--episodes", "100000", "--seed", "1"]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=ENV, stderr=subprocess.PIPE, text=True)
    time.sleep(12)  # imported, evaluating 100,000 episodes (minutes)
    proc.send_signal(sig)
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode == code and err == "interrupted; nothing was written\n", err


def until(proc, needle: str) -> str:
    """Read ``proc``'s output up to a line holding ``needle``; that line."""
    while needle not in (line := proc.stdout.readline()):
        assert line, f"the run ended before {needle!r}: " + proc.communicate()[1]
    return line


def own_tmp(tmp_path) -> dict:
    """A TMPDIR of the test's own, to see what multiprocessing leaves in it (pymp-*)."""
    (tmp_path / "tmp").mkdir()
    return {**ENV, "TMPDIR": str(tmp_path / "tmp")}


def test_a_closed_terminal_stops_the_run_as_kill_does(tmp_path):
    """SIGHUP (to the whole process group, as a closing terminal sends it): the closing line,
    exit 129, model.pt saved, no leaked semaphore, no multiprocessing temporary folder left."""
    proc, run_dir = start(
        tmp_path / "runs",
        *LONG_REACH,
        env=own_tmp(tmp_path),
        start_new_session=True,
    )
    until(proc, "evaluation of step")  # the worker is up
    os.killpg(proc.pid, signal.SIGHUP)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 129, err
    assert err.startswith("interrupted at step ") and "Traceback" not in err, err
    assert "leaked" not in err, err
    assert out.strip().splitlines()[-1].startswith("stopped: ") and "model.pt of step" in out
    assert checkpoint.load(os.path.join(run_dir, "model.pt"))["agent"]
    assert not list((tmp_path / "tmp").glob("pymp-*"))


def test_more_ctrl_c_during_the_clean_up_cannot_cut_it_short(tmp_path):
    """Ctrl-C, then again and again while the run saves and exits: one clean stop, nothing
    ignored in an exit handler, no temporary folder left."""
    proc, run_dir = start(
        tmp_path / "runs",
        *LONG_REACH,
        env=own_tmp(tmp_path),
    )
    until(proc, "evaluation of step")
    for _ in range(60):  # 3 s of Ctrl-C
        if proc.poll() is not None:
            break
        proc.send_signal(signal.SIGINT)
        time.sleep(0.05)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    assert err.startswith("interrupted at step "), err
    assert checkpoint.load(os.path.join(run_dir, "model.pt"))["agent"]
    assert not list((tmp_path / "tmp").glob("pymp-*"))


def evaluation_worker(pid: int) -> int:
    """The pid of ``pid``'s evaluation worker (spawned by multiprocessing), once it runs."""
    deadline = time.time() + 60
    while time.time() < deadline:
        for kid in children(pid):
            with open(f"/proc/{kid}/cmdline", "rb") as f:
                if b"spawn_main" in f.read():
                    return kid
        time.sleep(0.2)
    raise AssertionError("no evaluation worker started")


def test_training_goes_on_when_the_evaluation_worker_is_killed(tmp_path):
    """kill -9 of the worker: one warning line, every evaluation still logged, exit 0."""
    proc, run_dir = start(
        tmp_path, "--env-id", "FetchReach-v4", "--total-timesteps", "2000", "--eval-freq", "200", "--eval-episodes", "2"
    )
    until(proc, "evaluation of step 200 ")
    os.kill(evaluation_worker(proc.pid), signal.SIGKILL)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert "Traceback" not in err and err.count("evaluation worker died") == 1, err
    steps = [step for step, _ in scalars(run_dir)["eval/success_rate"]]
    assert steps == list(range(200, 2001, 200)), steps


def test_a_run_folder_turned_read_only_stops_in_one_line(monkeypatch, tmp_path, capsys):
    """As a full disk: the write that fails (here the second resume point, EPERM as under
    chattr +i) stops the run with one error line, exit 1, which says that model.pt could not be
    written either; the first resume point stays."""
    real_open, written = open, []

    def read_only(name, mode="r", *args, **kwargs):
        if "w" in mode and str(name).endswith(".tmp"):
            written.append(name)
            if len(written) > 1:
                raise PermissionError(errno.EPERM, os.strerror(errno.EPERM), str(name))
        return real_open(name, mode, *args, **kwargs)

    argv = [
        "ppo_kl.py",
        "--log-dir",
        str(tmp_path),
        *TINY_PPO,
        "--resume-freq",
        "256",
        "--save-model",
    ]
    monkeypatch.setattr(checkpoint, "open", read_only, raising=False)
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit) as stop:
        runpy.run_path(str(ROOT / "ppo_kl.py"), run_name="__main__")
    assert stop.value.code == 1
    captured = capsys.readouterr()
    errors = [line for line in captured.err.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in captured.err, captured.err
    assert "could not write" in errors[0] and errors[0].endswith(
        "resume.pt: Operation not permitted; model.pt not written either"
    ), errors[0]
    (run_dir,) = run_dirs(tmp_path)
    assert checkpoint._read(str(run_dir / "resume.pt"))["global_step"] == 256


@pytest.mark.parametrize("delay", [0.3, 0.6, 1.0, 2.0])
def test_ctrl_c_while_evaluate_starts_is_one_line(finished_run, delay):
    """Ctrl-C at any moment of ``python -m common.evaluate``'s start (torch's import, the task's
    checks, loading): one line, Ctrl-C's exit code."""
    cmd = [sys.executable, "-m", "common.evaluate", str(finished_run), "--episodes", "100000", "--seed", "1"]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=ENV, stderr=subprocess.PIPE, text=True)
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode in (130, -signal.SIGINT), err
    assert err == "interrupted; nothing was written\n", err


@pytest.mark.parametrize("script", ["ppo_kl.py", "qprop_ppo.py", "ipg_her.py", "ipg_her_recipe.py"])
def test_ctrl_c_while_a_script_imports_is_one_line(tmp_path, script):
    """Ctrl-C while torch and gymnasium load (each script imports ``common.cli`` first): one
    line, Ctrl-C's exit code, no run folder."""
    cmd = [sys.executable, str(ROOT / script), "--log-dir", str(tmp_path)]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=ENV, stderr=subprocess.PIPE, text=True)
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode in (130, -signal.SIGINT), err
    assert err == "interrupted; nothing was written\n", err
    assert not list(tmp_path.iterdir())


SWALLOWED = """import builtins, os, runpy, signal, sys, time
real_import = builtins.__import__
def importing(name, *args, **kwargs):
    if name == "torch" and "common.cli" in sys.modules and "torch" not in sys.modules:
        try:
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while torch loads...
            time.sleep(1)
        except BaseException:
            pass  # ...caught by a library that tries an import and goes on
    return real_import(name, *args, **kwargs)
builtins.__import__ = importing
sys.argv = {argv!r}
runpy.run_path({script!r}, run_name="__main__")
"""


def test_ctrl_c_while_a_library_loads_ends_the_script_even_if_the_library_catches_it(tmp_path):
    """A Ctrl-C while the libraries load ends the script there, in one line with Ctrl-C's exit
    code and no run folder, even where a library would catch the KeyboardInterrupt (or turn it
    into an ImportError, as mujoco's start-up does)."""
    argv = ["ipg_her.py", "--log-dir", str(tmp_path), *TINY]
    driver = SWALLOWED.format(argv=argv, script=str(ROOT / "ipg_her.py"))
    result = subprocess.run([sys.executable, "-c", driver], cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=120)
    assert result.returncode == 130, result.stderr
    assert result.stderr == "interrupted; nothing was written\n", result.stderr
    assert not list(tmp_path.iterdir())


DRIVER = """import runpy, sys
import torch
def interrupted(*args, **kwargs):
    raise KeyboardInterrupt  # Ctrl-C while resume.pt loads
torch.load = interrupted
sys.argv = {argv!r}
runpy.run_path({script!r}, run_name="__main__")
"""


def test_ctrl_c_while_a_resume_point_loads_is_one_line(finished_run, tmp_path):
    argv = [
        "ipg_her.py",
        "--log-dir",
        str(tmp_path),
        *TINY,
        "--save-model",
        "--resume-freq",
        "100",
        "--resume",
        str(finished_run),
    ]
    driver = DRIVER.format(argv=argv, script=str(ROOT / "ipg_her.py"))
    result = subprocess.run([sys.executable, "-c", driver], cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=120)
    assert result.returncode in (130, -signal.SIGINT), result.stderr
    assert result.stderr == "interrupted; nothing was written\n", result.stderr
