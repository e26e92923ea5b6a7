"""``--track`` (common/tracking.py): a run in Weights & Biases, read back from its offline record;
the refusals; a W&B failure costs the run nothing; without ``--track`` wandb is never imported."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ROOT, assert_clean_error, run_dirs, scalars
from test_evaluate import osmesa_available

pytest.importorskip("wandb")
from wandb.proto import wandb_internal_pb2  # noqa: E402

TINY = ("--env-id", "FetchReach-v4", "--total-timesteps", "200", "--eval-freq", "0", "--eval-episodes", "2")


def tracked(log_dir: Path, *flags: str, mode: str | None = "offline", **env):
    """``ipg_her.py`` in a subprocess, W&B in ``mode`` (None: online) with no account: none of
    the user's W&B variables, an empty HOME (no .netrc, no settings file), then ``env``."""
    home = log_dir.parent / "home"
    home.mkdir(exist_ok=True)
    env = {k: v for k, v in os.environ.items() if not k.startswith("WANDB_")} | env
    env |= {"OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore", "HOME": str(home)}
    env |= {"WANDB_MODE": mode} if mode else {}
    cmd = [sys.executable, str(ROOT / "ipg_her.py"), "--log-dir", str(log_dir), *flags]
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)


def run_folder(log_dir: Path) -> Path:
    """The one run folder in ``log_dir`` (beside W&B's ``wandb`` folder)."""
    (run_dir,) = [d for d in run_dirs(log_dir) if "__" in d.name]
    return run_dir


def records(path: Path):
    """The records of a ``.wandb`` file: W&B's header (``:W&B``, magic, version: 7 bytes), then
    LevelDB's log format, 32 KiB blocks of chunks (CRC 4, length 2, type 1: full, first,
    middle, last), each record a ``wandb_internal_pb2.Record``."""
    data, block = path.read_bytes(), 32768
    assert data[:4] == b":W&B", data[:8]
    pos, part = 7, b""
    while pos + 7 <= len(data):
        if block - pos % block < 7:  # a block's tail too short for a header is padding
            pos += block - pos % block
            continue
        length, kind = int.from_bytes(data[pos + 4 : pos + 6], "little"), data[pos + 6]
        part += data[pos + 7 : pos + 7 + length]
        pos += 7 + length
        if kind in (1, 4):  # a whole record, or its last chunk
            record = wandb_internal_pb2.Record()
            record.ParseFromString(part)
            part = b""
            yield record


def offline_record(log_dir: Path) -> dict:
    """What a tracked run's offline record holds: its id, config, history rows, saved files."""
    (run,) = (log_dir / "wandb").glob("offline-run-*")
    out = {"id": run.name.rpartition("-")[2], "dir": run, "config": {}, "history": [], "files": []}
    for record in records(next(run.glob("*.wandb"))):
        kind = record.WhichOneof("record_type")
        if kind == "run":
            out["config"] |= {u.key: u.value_json for u in record.run.config.update}
        elif kind == "history":
            out["history"].append({i.key or "/".join(i.nested_key) for i in record.history.item})
        elif kind == "files":
            out["files"] += [f.path for f in record.files.files]
    return out


def test_a_tracked_run_offline_holds_its_config_scalars_and_code(tmp_path):
    result = tracked(tmp_path, *TINY, "--track", "--wandb-project-name", "tests")
    assert result.returncode == 0, result.stderr
    run_dir = run_folder(tmp_path)
    record = offline_record(tmp_path)
    assert record["config"]["env_id"] == '"FetchReach-v4"', record["config"].get("env_id")
    assert record["config"]["total_timesteps"] == "200"
    for tag in ("charts/episodic_return", "charts/SPS"):
        assert any(tag in row for row in record["history"]), tag
        assert tag in scalars(run_dir)  # TensorBoard keeps it too
    assert "code/ipg_her.py" in record["files"]
    saved = record["dir"] / "files" / "code" / "ipg_her.py"
    assert saved.read_text() == (ROOT / "ipg_her.py").read_text()


def test_a_resumed_run_goes_on_in_its_w_and_b_run(tmp_path):
    flags = (*TINY[:2], *TINY[4:], "--track", "--resume-freq", "100")
    assert tracked(tmp_path / "first", *flags, "--total-timesteps", "200").returncode == 0
    log_dir = tmp_path / "first"
    run_dir = run_folder(log_dir)
    first = offline_record(log_dir)["id"]
    os.rename(log_dir / "wandb", tmp_path / "wandb-first")
    result = tracked(log_dir, *flags, "--total-timesteps", "300", "--resume", str(run_dir))
    assert result.returncode == 0, result.stderr
    assert offline_record(log_dir)["id"] == first


def test_videos_of_a_tracked_run_are_uploaded(tmp_path):
    if not osmesa_available():
        if os.environ.get("CI"):
            pytest.fail("CI must install the video backend (libosmesa6 and moviepy)")
        pytest.skip("no OSMesa renderer here: apt install libosmesa6")
    flags = (*TINY[:-1], "1", "--critic-steps", "1", "--track", "--capture-video")
    result = tracked(tmp_path, *flags, MUJOCO_GL="osmesa")
    assert result.returncode == 0, result.stderr
    files = offline_record(tmp_path)["files"]
    assert any(f.startswith("videos/step200/") and f.endswith(".mp4") for f in files), files


def without_wandb(tmp_path: Path) -> dict:
    """An environment in which ``import wandb`` fails, as where it is not installed."""
    (tmp_path / "sitecustomize.py").write_text("import sys\nsys.modules['wandb'] = None\n")
    return {"PYTHONPATH": str(tmp_path)}


def broken_wandb(tmp_path: Path) -> dict:
    """An environment whose wandb is found but fails to import, as a broken install does."""
    (tmp_path / "wandb.py").write_text("raise ImportError('a broken install')\n")
    return {"PYTHONPATH": str(tmp_path)}


@pytest.mark.parametrize("environment", [without_wandb, broken_wandb])
def test_track_without_wandb_is_one_line_before_any_run_folder(tmp_path, environment):
    result = tracked(tmp_path / "runs", *TINY, "--track", **environment(tmp_path))
    assert_clean_error(result, "--track needs wandb", "pip install wandb==0.31.0")
    assert not (tmp_path / "runs").exists()


def test_without_track_wandb_is_never_imported(tmp_path):
    """wandb made unimportable: an untracked run must not notice."""
    result = tracked(tmp_path / "runs", *TINY, **without_wandb(tmp_path))
    assert result.returncode == 0, result.stderr
    assert not (tmp_path / "runs" / "wandb").exists()


@pytest.mark.parametrize("flag", [["--wandb-entity", "me"], ["--wandb-project-name", "p"]])
def test_a_wandb_flag_without_track_is_refused(tmp_path, flag):
    result = tracked(tmp_path / "runs", *TINY, *flag)
    assert_clean_error(result, "would be ignored without --track")
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    "online_env, why",
    [
        ({}, "not logged in"),  # no account: never a prompt
        (  # an account, and a server that does not answer
            {
                "WANDB_API_KEY": "a" * 40,
                "WANDB_BASE_URL": "http://127.0.0.1:9",
                "WANDB_INIT_TIMEOUT": "5",
            },
            "W&B did not start",
        ),
    ],
)
def test_a_w_and_b_failure_is_one_line_and_the_run_goes_on(tmp_path, online_env, why):
    result = tracked(tmp_path, *TINY, "--track", mode=None, **online_env)
    assert result.returncode == 0, result.stderr
    warnings = [line for line in result.stdout.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and why in warnings[0], result.stdout
    assert "charts/SPS" in scalars(run_folder(tmp_path))


def test_ctrl_c_ends_a_tracked_run_as_an_untracked_one(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "WANDB_MODE": "offline", "HOME": str(tmp_path)}
    cmd = [sys.executable, str(ROOT / "ipg_her.py"), "--log-dir", str(tmp_path / "runs"), "--track", *TINY[:3], "100000"]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not list((tmp_path / "runs").glob("*__*/events.out.tfevents*")):
        assert time.time() < deadline and proc.poll() is None, proc.communicate()
        time.sleep(0.5)
    time.sleep(3)  # training under way
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "interrupted at step" in err and "Traceback" not in err, err


def test_the_runner_forwards_track_with_the_suite_as_the_group(monkeypatch, capsys):
    from benchmarks import run

    monkeypatch.delenv("WANDB_RUN_GROUP", raising=False)
    assert run.main(run.Args(suite="quick", track=True, dry_run=True)) == 0
    commands = [line for line in capsys.readouterr().out.splitlines() if "--env-id" in line]
    assert commands and all(line.split()[-1] == "--track" for line in commands), commands
    assert os.environ["WANDB_RUN_GROUP"] == "quick"


def test_the_install_line_is_the_pinned_wandb():
    from benchmarks import run
    from common import tracking

    pins = (ROOT / "requirements-test.txt").read_text().split()
    assert run.WANDB in pins and tracking.INSTALL == f"pip install {run.WANDB}"
