"""Shared test helpers: run a script in a subprocess, read back its TensorBoard scalars, parse
and check a command line in-process as a script does, a folder made read-only for a while, and a
random on-policy batch for the update functions; no test leaves a process running or its
scripts deaf to Ctrl-C."""

import contextlib
import inspect
import os
import signal
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# Started in the background by a script (`pytest ... &`), a test run inherits Ctrl-C ignored, and so
# would every script it starts (Python keeps an ignored SIGINT ignored): the Ctrl-C tests would send
# a signal no one hears. The tests press Ctrl-C as a terminal does, so their scripts get it back.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def run_script(script: str, log_dir: Path, *flags: str, timeout: int = 600) -> subprocess.CompletedProcess:
    """``python {script} --log-dir {log_dir} {flags}`` from the project root, output captured."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    cmd = [sys.executable, str(ROOT / script), "--log-dir", str(log_dir), *flags]
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)


def run_dirs(log_dir: Path) -> list[Path]:
    return sorted(p for p in Path(log_dir).iterdir() if p.is_dir())


def smoke_run(script: str, log_dir: Path, env_id: str, *flags: str) -> tuple[Path, dict]:
    """Train ``script`` on ``env_id`` with a tiny budget (``flags``): it must exit 0 into one
    run folder. Returns that folder and its scalars."""
    result = run_script(script, log_dir, "--env-id", env_id, *flags)
    assert result.returncode == 0, result.stderr
    (run_dir,) = run_dirs(log_dir)
    return run_dir, scalars(run_dir)


def scalars(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar tag of a run folder's event file(s): tag -> [(step, value), ...]."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def assert_clean_error(result: subprocess.CompletedProcess, *needles: str) -> None:
    """Bad input: non-zero exit, no traceback, one 'error:' line naming the problem."""
    assert result.returncode != 0, result.stdout
    assert "Traceback" not in result.stderr, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


def parse(module, *argv: str):
    """Parse and check ``argv`` as ``module``'s ``__main__`` does, then fill in what follows from the task where the
    script does (the recipe's ``fill_in``); the ``Args``."""
    from common import cli

    argv = list(argv)
    args = cli.parse_args(module.Args, argv)
    takes_argv = len(inspect.signature(module.check_args).parameters) > 1  # ppo_kl's: args only
    module.check_args(*(args, argv)[: 1 + takes_argv])
    if hasattr(module, "fill_in"):
        module.fill_in(args)
    return args


def refused(capsys, module, *argv: str) -> str:
    """The one ``error:`` line (exit 2, nothing else on stderr) that ``parse`` refuses ``argv``
    with."""
    with pytest.raises(SystemExit) as exit_info:
        parse(module, *argv)
    assert exit_info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0]


@contextlib.contextmanager
def read_only(folder: Path):
    """``folder`` made read-only for a while: chmod 555, or for root (whom it does not stop)
    chattr +i; the test is skipped where root may not use chattr."""
    folder.chmod(0o555)
    immutable = os.access(folder, os.W_OK)  # root
    if immutable and subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode:
        folder.chmod(0o755)
        pytest.skip("root, and chattr +i is not permitted here")
    try:
        yield folder
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(folder)], check=True)
        folder.chmod(0o755)


@pytest.fixture(autouse=True)
def signal_handlers():
    """A script run in-process leaves its stop signals ignored (common/run.py: until its exit);
    the next test gets pytest's handlers back."""
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    yield
    for s, handler in saved.items():
        signal.signal(s, handler)


def children(pid: int) -> set[int]:
    """Every descendant of ``pid`` still in /proc (Linux)."""
    found = set()
    with contextlib.suppress(FileNotFoundError):  # an ended process has no children
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                found |= {int(c) for c in f.read().split()}
    return found | {g for c in found for g in children(c)}


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ")[1][0] != "Z"  # a zombie has ended
    except FileNotFoundError:
        return False


@pytest.fixture(autouse=True)
def no_process_outlives_its_test():
    """A test that fails while its script runs (an assert, a timeout) leaves the script running,
    a load that fails the tests after it: what it started is killed when it ends (not
    multiprocessing's resource tracker, which the test process keeps)."""
    before = children(os.getpid())
    yield
    for pid in children(os.getpid()) - before:
        with contextlib.suppress(OSError):
            if b"resource_tracker" not in Path(f"/proc/{pid}/cmdline").read_bytes():
                os.kill(pid, signal.SIGKILL)


@pytest.fixture(scope="session")
def root() -> Path:
    return ROOT


def random_batch(n: int, obs_dim: int, act_dim: int, agent, seed: int = 0) -> dict:
    """An on-policy batch as ``make_batch`` returns it: actions sampled from ``agent``'s policy,
    random advantages and returns."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(n, obs_dim, generator=g)
    with torch.no_grad():
        pi = agent.dist(obs)
        actions = pi.mean + pi.stddev * torch.randn(n, act_dim, generator=g)
        logprobs = pi.log_prob(actions).sum(-1)
        return {
            "obs": obs,
            "actions": actions,
            "logprobs": logprobs,
            "mean": pi.mean,
            "std": pi.stddev,
            "advantages": torch.randn(n, generator=g),
            "returns": torch.randn(n, generator=g),
        }


class ScaledQ(torch.nn.Module):
    """The critic of a task whose rewards are all multiplied by c."""

    def __init__(self, qf, c):
        super().__init__()
        self.qf, self.c = qf, c

    def forward(self, x, a):
        return self.c * self.qf(x, a)


def assert_saved_policy_replays_last_evaluation(run_dir: Path, env_id: str) -> None:
    """The run's model.pt, loaded by ``common.evaluate.load_policy`` alone, replays the run's last
    evaluation to the same mean return, and acts on raw observations (a Dict on goal tasks)."""
    from common.evaluate import load_policy

    policy = load_policy(str(run_dir))
    returns, _ = policy.evaluate(policy.last_eval_seeds)
    last = scalars(run_dir)["eval/episodic_return"][-1][1]
    assert len(returns) > 0 and np.float32(returns.mean()) == np.float32(last), (returns, last)
    env = gym.make(env_id)
    obs, _ = env.reset(seed=0)
    action = policy(obs)
    assert action.shape == env.action_space.shape and env.action_space.contains(action)
