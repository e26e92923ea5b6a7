"""After training: common/checkpoint.py and common.evaluate (load, evaluate, watch), and
--capture-video really recording."""

import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from conftest import ROOT, assert_clean_error, run_dirs, run_script, scalars

import ipg_her
import qprop_ppo
from common import checkpoint, evaluate
from common.normalizer import RunningMeanStd

TINY_PPO = [
    "--num-envs",
    "2",
    "--num-steps",
    "64",
    "--total-timesteps",
    "128",
    "--num-minibatches",
    "2",
    "--update-epochs",
    "1",
    "--eval-episodes",
    "2",
]


@pytest.fixture(scope="module")
def hopper_run(tmp_path_factory):
    log_dir = tmp_path_factory.mktemp("runs")
    result = run_script("ppo_kl.py", log_dir, *TINY_PPO, "--save-model", "--resume-freq", "128")
    assert result.returncode == 0, result.stderr
    (run_dir,) = run_dirs(log_dir)
    return run_dir


def test_the_command_prints_the_runs_own_last_evaluation(hopper_run, capsys):
    assert evaluate.main([str(hopper_run)]) == 0
    last = scalars(hopper_run)["eval/episodic_return"][-1][1]
    assert capsys.readouterr().out.startswith(f"2 episodes: return {last:.2f} ± ")
    assert evaluate.main([str(hopper_run / "model.pt"), "--episodes", "3", "--seed", "4"]) == 0
    assert capsys.readouterr().out.startswith("3 episodes: return ")


def test_a_resume_file_or_a_folder_holding_only_one_evaluates_its_policy(hopper_run, tmp_path, capsys):
    """A run without --save-model: its resume.pt (here written at the end) replays the run's
    last evaluation like the model.pt does, also as the only file of a folder; on a goal task
    (FetchReach, its goal normaliser) too."""
    flags = ("--total-timesteps", "200", "--eval-episodes", "2", "--resume-freq", "100")
    assert run_script("ipg_her.py", tmp_path / "fetch", *flags).returncode == 0
    (fetch_run,) = run_dirs(tmp_path / "fetch")
    (tmp_path / "copy").mkdir()
    (tmp_path / "copy" / "resume.pt").write_bytes((hopper_run / "resume.pt").read_bytes())
    for path, run in ((hopper_run / "resume.pt", hopper_run), (tmp_path / "copy", hopper_run), (fetch_run, fetch_run)):
        last = scalars(run)["eval/episodic_return"][-1][1]
        assert evaluate.main([str(path)]) == 0
        assert capsys.readouterr().out.startswith(f"2 episodes: return {last:.2f} ± ")


def refused(capsys, *argv: str) -> str:
    with pytest.raises(SystemExit) as exit_info:
        evaluate.main(list(argv))
    assert exit_info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0]


class Payload:
    """A pickle that runs a shell command when unpickled (what a shared model file could hold)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_a_model_or_resume_file_that_would_run_code_is_refused_without_running_it(tmp_path):
    """model.pt through common.evaluate and load_policy, resume.pt through --resume: each is
    refused with one line, and the command it holds never runs (it would create the marker)."""
    marker = tmp_path / "PWNED"
    evil = {"format_version": checkpoint.FORMAT_VERSION, "agent": Payload(marker)}
    torch.save(evil, tmp_path / "model.pt")
    result = subprocess.run(
        [sys.executable, "-m", "common.evaluate", str(tmp_path / "model.pt")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert_clean_error(result, "was refused")
    with pytest.raises(checkpoint.CheckpointError, match="was refused"):
        evaluate.load_policy(str(tmp_path))
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    torch.save(evil | {"script": "ipg_her", "args": {}}, run_dir / "resume.pt")
    result = run_script("ipg_her.py", tmp_path / "logs", "--resume", str(run_dir), timeout=120)
    assert_clean_error(result, "was refused")
    assert not marker.exists(), "unpickling ran the file's command"


def test_the_policy_is_the_scripts_network_rebuilt_from_its_saved_layer_kinds(hopper_run, tmp_path, capsys):
    """The layer kinds saved beside the weights are data: the policy evaluate runs is the
    script's own actor (its forward pass, not a copy of it), a changed kind changes it, and a
    kind outside Linear/Tanh/ReLU or a missing one is refused in one line."""
    import ppo_kl

    content = torch.load(hopper_run / "model.pt", weights_only=True)
    assert content["agent_layers"]["actor_mean"] == ["Linear", "Tanh", "Linear", "Tanh", "Linear"]
    policy = evaluate.load_policy(str(hopper_run / "model.pt"))
    agent = ppo_kl.Agent(11, 3)  # ppo_kl.py: 64 hidden units
    agent.load_state_dict(content["agent"])
    obs = np.random.default_rng(0).normal(size=11).astype(np.float32) * 3
    with torch.no_grad():
        mean = agent.actor_mean(policy.inputs(obs))[0].numpy()
    np.testing.assert_array_equal(policy(obs), np.clip(mean, -1, 1))
    for kinds, works in (
        (["Linear", "ReLU", "Linear", "Tanh", "Linear"], True),
        (["Linear", "Tanh", "Linear", "Dropout", "Linear"], False),
        (["Linear", "Tanh", "Linear"], False),
        (None, False),
    ):
        content["agent_layers"]["actor_mean"] = kinds
        torch.save(content, tmp_path / "model.pt")
        if works:
            assert not np.array_equal(evaluate.load_policy(str(tmp_path))(obs), policy(obs))
        else:
            assert "actor_mean" in refused(capsys, str(tmp_path / "model.pt"))


def test_bad_input_gets_one_clear_line(hopper_run, tmp_path, capsys):
    assert "no such file" in refused(capsys, str(tmp_path / "nothing.pt"))
    assert "no model.pt or resume.pt" in refused(capsys, str(tmp_path))
    torch.save({"format_version": checkpoint.FORMAT_VERSION, "args": {}}, tmp_path / "args.pt")
    assert "holds no policy" in refused(capsys, str(tmp_path / "args.pt"))
    (tmp_path / "notes.pt").write_text("not a checkpoint")
    assert "not a checkpoint" in refused(capsys, str(tmp_path / "notes.pt"))
    torch.save({"script": "ppo_kl", "format_version": 99}, tmp_path / "future.pt")
    assert "format 99" in refused(capsys, str(tmp_path / "future.pt"))
    # a model.pt of the code before the teaching edition (format 1: numpy arrays pickled)
    normalizer = {"mean": np.zeros(11), "var": np.ones(11), "count": 1.0, "clip": 10.0}
    old = {
        "format_version": 1,
        "script": "ppo_kl",
        "args": {"env_id": "Hopper-v5"},
        "last_eval_seeds": [1],
        "normalizer": normalizer,
        "agent": {},
    }
    torch.save(old, tmp_path / "old.pt")
    assert "format 1's pickled arrays are refused" in refused(capsys, str(tmp_path / "old.pt"))
    assert "NoSuchEnv-v0" in refused(capsys, str(hopper_run), "--env-id", "NoSuchEnv-v0")
    assert "does not match" in refused(capsys, str(hopper_run), "--env-id", "FetchReach-v4")
    assert "--episodes" in refused(capsys, str(hopper_run), "--episodes", "0")


def renamed(run_dir, tmp_path, env_id: str):
    """A copy of ``run_dir``'s model.pt whose saved ``env_id`` names another task."""
    content = torch.load(run_dir / "model.pt", weights_only=True)
    content["args"]["env_id"] = env_id
    torch.save(content, tmp_path / "model.pt")
    return tmp_path / "model.pt"


def test_a_model_file_never_chooses_the_code_that_is_imported(hopper_run, tmp_path, capsys):
    """A saved ``module:Task`` is imported only when the user names it with --env-id: a model.pt
    naming ``this`` prints no Zen of Python, one naming a notes.py beside it does not run it;
    each says, in one line, which flag to pass. Passed, the module is imported."""
    (tmp_path / "notes.py").write_text(f"open({str(tmp_path / 'RAN')!r}, 'w').close()\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    for module in ("this", "notes"):
        path = renamed(hopper_run, tmp_path, f"{module}:Hopper-v5")
        cmd = [sys.executable, "-m", "common.evaluate", str(path)]
        result = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True)
        assert_clean_error(
            result, f"this policy was trained on {module}:Hopper-v5; pass --env-id {module}:Hopper-v5 to import {module}"
        )
        assert "Beautiful is better" not in result.stdout + result.stderr
        with pytest.raises(ValueError, match="pass --env-id"):
            evaluate.load_policy(str(path))
    assert not (tmp_path / "RAN").exists(), "the model file ran notes.py"
    with pytest.raises(ValueError, match="pass --env-id gone_module:Hopper-v5"):
        evaluate.load_policy(str(renamed(hopper_run, tmp_path, "gone_module:Hopper-v5")))
    line = refused(capsys, str(tmp_path / "model.pt"), "--env-id", "gone_module:Hopper-v5")
    assert "cannot import gone_module (ModuleNotFoundError" in line, line
    result = subprocess.run(
        [sys.executable, "-m", "common.evaluate", str(path), "--env-id", "notes:Hopper-v5", "--seed", "1", "--episodes", "1"],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0 and (tmp_path / "RAN").exists(), result.stderr


def test_a_task_evaluate_cannot_drive_is_one_line(hopper_run, tmp_path, monkeypatch, capsys):
    """Discrete actions, a missing dependency, mujoco-py, a user's module that raises."""
    (tmp_path / "raising.py").write_text("raise RuntimeError('broken on purpose')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for env_id, needle in (
        ("CartPole-v1", "Discrete actions"),
        ("CarRacing-v3", "not installed"),
        ("Hopper-v2", "mujoco-py"),
        ("raising:Task-v0", "cannot import raising (RuntimeError: broken"),
    ):
        assert needle in refused(capsys, str(hopper_run), "--env-id", env_id), env_id


def test_an_interrupted_save_leaves_the_previous_checkpoint_loadable(tmp_path, monkeypatch):
    path = str(tmp_path / "model.pt")
    agent = torch.nn.Linear(2, 2)
    args = type("Args", (), {"env_id": "Hopper-v5"})()
    model = dict(agent=agent, normalizer=RunningMeanStd((2,)))
    checkpoint.save(path, args, [1, 2], **model)

    real_open = open

    def killed_half_way(file, mode="r", *args, **kwargs):
        if "w" in mode:
            with real_open(file, mode) as f:
                f.write(b"half a checkpoint")
            raise KeyboardInterrupt
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr("builtins.open", killed_half_way)
    with pytest.raises(KeyboardInterrupt):
        checkpoint.save(path, args, [3], **model)
    monkeypatch.undo()
    assert os.listdir(tmp_path) == ["model.pt"], "the half-written temporary file is left"
    state = checkpoint.load(path)
    assert state["last_eval_seeds"] == [1, 2]
    torch.testing.assert_close(state["agent"]["weight"], agent.weight.detach())


def osmesa_available() -> bool:
    code = "import mujoco; mujoco.GLContext(8, 8)"
    env = {**os.environ, "MUJOCO_GL": "osmesa"}
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True).returncode == 0


@pytest.mark.parametrize(
    "script, flags",
    [
        ("ppo_kl.py", ["--env-id", "Hopper-v5", *TINY_PPO[:-1], "1"]),
        (
            "ipg_her.py",
            [
                "--env-id",
                "FetchReach-v4",
                "--total-timesteps",
                "100",
                "--critic-steps",
                "1",
                "--eval-episodes",
                "1",
            ],
        ),
    ],
)
def test_capture_video_records_an_mp4_with_frames(tmp_path, script, flags):
    """One short evaluation of each task family, recorded with MuJoCo's OSMesa renderer (CI
    installs it: apt install libosmesa6; pip install moviepy)."""
    if not osmesa_available():
        if os.environ.get("CI"):
            pytest.fail("CI must install the video backend (libosmesa6 and moviepy)")
        pytest.skip("no OSMesa renderer here: apt install libosmesa6")
    env = {**os.environ, "MUJOCO_GL": "osmesa", "OMP_NUM_THREADS": "1"}
    cmd = [
        sys.executable,
        str(ROOT / script),
        "--log-dir",
        str(tmp_path),
        "--capture-video",
        *flags,
    ]
    result = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    (run_dir,) = run_dirs(tmp_path)
    videos = sorted((run_dir / "videos").rglob("*.mp4"))
    assert videos, list((run_dir / "videos").rglob("*"))
    import imageio

    frames = imageio.get_reader(str(videos[0]), "ffmpeg").count_frames()
    assert frames > 10, frames
    assert np.all([v.stat().st_size > 1000 for v in videos])


@pytest.mark.parametrize("workers", [0, 1])
def test_background_evaluator_returns_results_in_submission_order(workers):
    """The worker changes when an evaluation runs, not what it returns or in what order; the
    arguments are copied at submission (a snapshot, whatever training does next)."""
    from common.background import BackgroundEvaluator

    evaluator = BackgroundEvaluator(workers)
    weights = np.array([1.0, 2.0])
    for step in (100, 200, 300):
        evaluator.submit(step, np.multiply, weights, step)
        weights += 1.0  # training moves on
    done = evaluator.finished(wait=True)
    evaluator.close()
    assert [step for step, _ in done] == [100, 200, 300]
    for (_, result), expected in zip(done, ([100, 200], [400, 600], [900, 1200]), strict=True):
        np.testing.assert_array_equal(result, expected)


def test_background_evaluator_closes_its_worker_before_returning_once_nothing_is_pending():
    """A pool left winding down when the run exits races the interpreter's own shutdown (on
    Python 3.11 an ``OSError: [Errno 9] Bad file descriptor`` at the end of a finished run)."""
    import multiprocessing

    from common.background import BackgroundEvaluator

    evaluator = BackgroundEvaluator(1)
    evaluator.submit(100, np.multiply, 2.0, 3.0)
    assert evaluator.finished(wait=True) == [(100, 6.0)]
    evaluator.close()
    assert multiprocessing.active_children() == []


def test_background_evaluator_sends_tensors_under_a_deep_tmpdir(tmp_path):
    """A snapshot of tensors reaches the worker whatever the TMPDIR: torch's pickler would share
    them through a socket there, whose path AF_UNIX caps at 108 bytes."""
    tmpdir = tmp_path / ("d" * max(1, 100 - len(str(tmp_path))))
    tmpdir.mkdir()
    code = (
        "import torch\n"
        "from common.background import BackgroundEvaluator\n"
        "evaluator = BackgroundEvaluator(1, warn=print)\n"
        "evaluator.submit(100, torch.mul, {'w': torch.ones(3)}['w'], 2.0)\n"
        "print(evaluator.finished(wait=True)[0][1].tolist())\n"
        "evaluator.close()\n"
    )
    env = {**os.environ, "TMPDIR": str(tmpdir)}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
    assert done.returncode == 0 and done.stdout == "[2.0, 2.0, 2.0]\n", done.stdout + done.stderr


def test_resume_accepts_flags_added_since_at_their_defaults_and_refuses_a_jumping_schedule(
    tmp_path,
):
    """A resume point written before a flag existed: the run had the flag's default, so the
    same command resumes it, and only a non-default value is refused. A longer budget is refused
    under --anneal-lr (Q-Prop's, PPO-KL's), whose schedule it would move."""
    fields = dict.fromkeys(checkpoint.RESUME_FIELDS[2:], 0)  # beside the script and its args
    checkpoint.save_resume_state(str(tmp_path), ipg_her.Args(), **fields | {"global_step": 100})
    state = torch.load(tmp_path / "resume.pt", weights_only=False)
    del state["args"]["q_bar"]  # as written by code before --q-bar
    torch.save(state, tmp_path / "resume.pt")
    assert checkpoint.load_resume_state(str(tmp_path), ipg_her.Args())["global_step"] == 100
    with pytest.raises(checkpoint.CheckpointError, match="--q-bar 'mean' \\(now 'sample'\\)"):
        checkpoint.load_resume_state(str(tmp_path), ipg_her.Args(q_bar="sample"))
    checkpoint.save_resume_state(str(tmp_path), qprop_ppo.Args(anneal_lr=True), **fields)
    checkpoint.load_resume_state(str(tmp_path), qprop_ppo.Args(anneal_lr=True, resume_freq=9))
    checkpoint.load_resume_state(str(tmp_path), qprop_ppo.Args(anneal_lr=True, exp_name="renamed"))
    with pytest.raises(checkpoint.CheckpointError, match="--anneal-lr"):
        checkpoint.load_resume_state(str(tmp_path), qprop_ppo.Args(anneal_lr=True, total_timesteps=9))
