"""common/cli.py and each script's own argument checks, in-process: bad input exits with one
``error:`` line naming the problem, before any run folder exists."""

import os
import subprocess
import sys

import pytest
from conftest import ROOT, assert_clean_error, run_dirs, run_script

import ipg_her
import ppo_kl
import qprop_ppo
from common import cli
from common.run import start_run

SCRIPTS = {"ppo_kl": ppo_kl, "qprop_ppo": qprop_ppo, "ipg_her": ipg_her}


def refused(capsys, script, *argv: str) -> str:
    """Parse and check ``argv`` as ``script`` would; return the one error line it exits with."""
    module = SCRIPTS[script]
    with pytest.raises(SystemExit) as exit_info:
        args = cli.parse_args(module.Args, list(argv))
        module.check_args(args) if module is ppo_kl else module.check_args(args, list(argv))
    assert exit_info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0]


@pytest.mark.parametrize("script", SCRIPTS)
@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--env-id", "NoSuchEnv-v0"], "NoSuchEnv-v0"),
        (["--total-timesteps", "0"], "--total-timesteps must be positive"),
        (["--num-envs", "-1"], "--num-envs must be positive"),
        (["--eval-episodes", "0"], "--eval-episodes must be positive"),
        (["--num-steps", "10", "--total-timesteps", "5"], "less than one batch"),
        (["--num-envs", "1", "--num-steps", "10", "--num-minibatches", "3"], "minibatches"),
        (["--gamma", "1.5"], "--gamma"),
        (["--gae-lambda", "-0.1"], "--gae-lambda"),
        (["--kl-target", "0"], "--kl-target"),
        (["--seed", "one"], "--seed"),  # a parse error, reduced to one line
    ],
)
def test_common_checks(capsys, script, argv, needle):
    assert needle in refused(capsys, script, *argv)


@pytest.mark.parametrize(
    "script, argv, needle",
    [
        ("qprop_ppo", ["--eta-mode", "foo"], "foo"),
        ("qprop_ppo", ["--tau", "-0.1"], "--tau"),
        ("qprop_ppo", ["--critic-steps", "-1"], "--critic-steps"),
        ("qprop_ppo", ["--critic-batch-size", "0"], "--critic-batch-size"),
        ("ipg_her", ["--nu", "1.5"], "--nu"),
        ("ipg_her", ["--tau", "0"], "--tau"),
        ("ipg_her", ["--her-goal-selection-strategy", "foo"], "foo"),
        ("ipg_her", ["--off-policy-batch-size", "0"], "--off-policy-batch-size"),
        ("ipg_her", ["--env-id", "Hopper-v5", "--her"], "--her would be ignored"),
        ("ipg_her", ["--env-id", "Hopper-v5", "--her-n-sampled-goal", "2"], "not a goal task"),
        ("ipg_her", ["--no-her", "--her-n-sampled-goal", "2"], "ignored (--no-her)"),
        ("ipg_her", ["--no-her", "--her-goal-selection-strategy=final"], "ignored (--no-her)"),
        ("ipg_her", ["--off-policy-states", "batch", "--off-policy-batch-size", "64"], "ignored"),
        ("ipg_her", ["--buffer-size", "10"], "less than one FetchReach-v4 episode (50 steps)"),
        ("qprop_ppo", ["--buffer-size", "3000"], "less than one Hopper-v5 episode (1000 steps)"),
        ("ipg_her", ["--hidden", "0"], "--hidden must be positive"),
        ("ipg_her", ["--nu", "0", "--action-l2", "1"], "--action-l2 would be ignored"),
        ("ipg_her", ["--nu", "0", "--twin-critic"], "--twin-critic would be ignored"),
        ("ipg_her", ["--nu", "0", "--critic-target", "sample"], "--critic-target would be ignored"),
        ("qprop_ppo", ["--eta-mode", "none", "--twin-critic"], "--twin-critic would be ignored"),
        ("ipg_her", ["--nu", "0", "--bounds-loss", "1"], "--bounds-loss would be ignored"),
        ("ipg_her", ["--action-l2", "-1"], "--action-l2 must be non-negative, got -1.0"),
        ("ipg_her", ["--bounds-loss", "-1"], "--bounds-loss must be non-negative, got -1.0"),
        ("ipg_her", ["--target-std", "0"], "--target-std must be positive, got 0.0"),
        ("ipg_her", ["--target-std", "1", "-1", "1", "1"], "--target-std must be positive"),
        ("ipg_her", ["--target-std", "1", "0.3"], "one per action dimension (4 on FetchReach-v4)"),
        ("qprop_ppo", ["--critic-hidden", "0"], "--critic-hidden must be positive"),
    ],
)
def test_algorithm_checks(capsys, script, argv, needle):
    assert needle in refused(capsys, script, *argv)


@pytest.mark.parametrize("script", SCRIPTS)
def test_defaults_pass_the_checks(script):
    module = SCRIPTS[script]
    args = cli.parse_args(module.Args, [])
    module.check_args(args) if module is ppo_kl else module.check_args(args, [])
    assert args.env_id in ("Hopper-v5", "FetchReach-v4")


def test_checks_do_not_modify_args():
    args = cli.parse_args(ipg_her.Args, ["--env-id", "Hopper-v5"])
    before = vars(args).copy()
    ipg_her.check_args(args, ["--env-id", "Hopper-v5"])
    assert vars(args) == before


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--env-id", "CartPole-v1"], "Discrete actions"),
        (["--env-id", "FrozenLake-v1"], "Discrete actions"),
        (["--env-id", "FrankaKitchen-v1"], "observations are not supported"),
        (["--env-id", "CarRacing-v3"], "not installed"),
        (["--env-id", "Hopper-v2"], "mujoco-py"),
        (["--learning-rate", "-1"], "--learning-rate must be positive"),
        (["--seed", "-1"], "--seed must be non-negative"),
        (["--save-freq", "-5"], "--save-freq"),
        (["--batch-size", "64"], "--batch-size"),  # computed, not a flag
        (["--total-timestep", "3000"], "unrecognized option --total-timestep, 3000; did you mean"),
        (["--env-id", "Hoper-v5"], "did you mean Hopper-v5?"),
        (["--num-envs", "100000", "--total-timesteps", "1000000000"], "GiB are free"),
    ],
)
@pytest.mark.parametrize("script", SCRIPTS)
def test_tasks_and_values_the_scripts_cannot_use(capsys, script, argv, needle):
    assert needle in refused(capsys, script, *argv)


@pytest.mark.parametrize("script", ["qprop_ppo", "ipg_her"])
def test_critic_learning_rate_must_be_positive(capsys, script):
    assert "--critic-learning-rate" in refused(capsys, script, "--critic-learning-rate", "-1")


def test_an_uncreatable_log_dir_is_refused_and_run_folders_are_unique(capsys, tmp_path):
    args = cli.parse_args(ppo_kl.Args, ["--log-dir", "/proc/no/such/dir"])
    with pytest.raises(SystemExit):
        start_run(args)
    assert capsys.readouterr().err.startswith("error: cannot create the run folder")
    args = cli.parse_args(ppo_kl.Args, ["--log-dir", str(tmp_path)])
    folders = [start_run(args) for _ in range(3)]  # the same second, the same seed
    assert len(set(folders)) == 3


@pytest.mark.parametrize("script", SCRIPTS)
def test_bad_input_end_to_end_fails_with_one_clear_line_and_no_run_folder(tmp_path, script):
    """The same check run as a user runs it: a subprocess, one line, no run folder."""
    result = run_script(f"{script}.py", tmp_path, "--total-timesteps", "0", timeout=60)
    assert_clean_error(result, "--total-timesteps")
    assert not (tmp_path.exists() and run_dirs(tmp_path)), "no run folder for rejected input"


def test_a_budget_that_is_not_whole_batches_says_what_it_runs(tmp_path):
    """Training runs in whole batches: the first lines say so, with the steps it will run."""
    flags = ("--env-id", "Hopper-v5", "--total-timesteps", "700", "--num-envs", "2",
             "--num-steps", "128", "--num-minibatches", "2", "--update-epochs", "1",
             "--eval-freq", "0", "--eval-episodes", "1")  # fmt: skip
    result = run_script("ppo_kl.py", tmp_path, *flags)
    assert result.returncode == 0, result.stderr
    assert "--total-timesteps 700: 512 steps, whole batches of 256" in result.stdout
    assert "evaluation of step 512 (mean policy): eval_return=" in result.stdout


def test_a_renderer_that_cannot_load_is_refused_before_training(tmp_path):
    """MuJoCo loads MUJOCO_GL's renderer on import (osmesa without libosmesa6 raised a 38-line
    traceback even for plain training); an unknown one takes the same path."""
    env = {**os.environ, "MUJOCO_GL": "no-such-renderer"}
    result = subprocess.run([sys.executable, str(ROOT / "ppo_kl.py"), "--log-dir", str(tmp_path)],
                            env=env, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert_clean_error(result, "MUJOCO_GL=no-such-renderer", "unset MUJOCO_GL")
    assert not tmp_path.exists() or not run_dirs(tmp_path)


def test_a_tasks_own_defaults_apply_where_no_flag_was_given(capsys):
    """ipg_her.py's TASK_DEFAULTS: FetchPush takes them, a flag given wins, FetchReach keeps the
    Args defaults; one line names what was taken."""

    def parse(*argv):
        return cli.parse_args(ipg_her.Args, list(argv), task_defaults=ipg_her.TASK_DEFAULTS)

    push = parse("--env-id", "FetchPush-v4", "--hidden=64")
    taken = (push.hidden, push.target_std, push.normalization, push.action_l2)
    assert taken == (64, 1.0, "paper", 1.0)
    line = "own defaults: --target-std 1.0, --normalization paper, --action-l2 1.0, --twin-critic\n"
    assert capsys.readouterr().out.endswith(line)  # spelled as one would type them
    assert vars(parse("--env-id", "FetchReach-v4")) == vars(ipg_her.Args())
    assert capsys.readouterr().out == ""
    assert parse("--env-id", "FetchPush-v4").twin_critic  # a boolean default of the task's
    assert not parse("--env-id", "FetchPush-v4", "--no-twin-critic").twin_critic  # the flag wins
    assert parse("--env-id", "FetchPickAndPlace-v4").target_std == (1.0, 1.0, 1.0, 0.3)
    assert "--target-std 1.0 1.0 1.0 0.3," in capsys.readouterr().out  # a tuple as typed
    slide = parse("--env-id", "FetchSlide-v4")  # Push's, but narrow sigma and mu kept in bounds
    assert (slide.target_std, slide.action_l2, slide.bounds_loss) == ((0.3, 0.3, 0.3, 1.0), 0, 1)
    assert (slide.hidden, slide.normalization, slide.twin_critic) == (256, "paper", True)
    assert slide.anneal_lr and not parse("--env-id", "FetchPush-v4").anneal_lr  # Slide's only
