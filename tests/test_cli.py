"""common/cli.py and each script's own argument checks: bad input exits with one ``error:``
line naming the problem, before any run folder exists. Flags in any spelling, flags a run would
ignore (IPG at nu = 0 and 1, Q-Prop without a critic), nan and inf, tyro's parse errors, the
task's defaults; in-process, plus a few runs as a user runs them (one line, no run folder)."""

import dataclasses
import os
import subprocess
import sys
import typing

import gymnasium as gym
import numpy as np
import pytest
from conftest import (
    ROOT,
    assert_clean_error,
    parse,
    refused,
    run_dirs,
    run_script,
    scalars,
)

import ipg_her
import ipg_her_recipe
import ppo_kl
import qprop_ppo
from common import cli, tasks
from common.run import start_run

SCRIPTS = {"ppo_kl": ppo_kl, "qprop_ppo": qprop_ppo, "ipg_her": ipg_her, "ipg_her_recipe": ipg_her_recipe}


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
        (["--torch-threads", "0"], "--torch-threads must be positive, got 0"),
        (["--max-grad-norm", "-1"], "--max-grad-norm must be positive, got -1.0"),
        (["--max-grad-norm", "0"], "--max-grad-norm must be positive, got 0.0"),
        (["--vf-coef", "-1"], "--vf-coef must be positive, got -1.0"),
        (
            ["--save-freq", "1000"],
            "--save-freq 1000 would be ignored (it saves model.pt, which "
            "only --save-model writes): add --save-model or leave it out",
        ),
        (["--exp-name", "../../x"], "--exp-name '../../x' must be a plain name, without '/'"),
        (["--exp-name", "a/b"], "--exp-name 'a/b' must be a plain name"),
    ],
)
def test_common_checks(capsys, script, argv, needle):
    """Tasks and values none of the scripts can use (``cli.check_run`` and each script's own)."""
    assert needle in refused(capsys, SCRIPTS[script], *argv)


NOT_A_GOAL_TASK = "would be ignored (Hopper-v5 is not a goal task): leave it out"
NU_0 = "would be ignored (at --nu 0 without --use-cv no term uses the critic): leave it out"
UNRECOGNIZED = "unrecognized option {} (--help lists them)"


# each error names only its flag and its value (and what it expects)
@pytest.mark.parametrize(
    "script, argv, line",
    [
        ("ppo_kl", ["--gamma", "1.5"], "--gamma must be in (0, 1], got 1.5"),
        ("ppo_kl", ["--gae-lambda", "-0.1"], "--gae-lambda must be in [0, 1], got -0.1"),
        ("ppo_kl", ["--kl-target", "0"], "--kl-target must be positive, got 0.0"),
        ("ppo_kl", ["--beta-init", "-1"], "--beta-init must be non-negative, got -1.0"),
        ("qprop_ppo", ["--gamma", "0"], "--gamma must be in (0, 1], got 0.0"),
        (
            "qprop_ppo",
            ["--eta-mode", "foo"],
            "--eta-mode expects one of (batch-conservative, "
            "batch-aggressive, conservative, aggressive, ones, none), got 'foo'",
        ),
        ("qprop_ppo", ["--tau", "-0.1"], "--tau must be in (0, 1], got -0.1"),
        ("qprop_ppo", ["--critic-steps", "-1"], "--critic-steps must be non-negative, got -1"),
        ("qprop_ppo", ["--critic-batch-size", "0"], "--critic-batch-size must be positive, got 0"),
        ("qprop_ppo", ["--critic-hidden", "0"], "--critic-hidden must be positive, got 0"),
        (
            "qprop_ppo",
            ["--buffer-size", "3000"],
            "--buffer-size 3000 keeps 750 steps per env, less than one Hopper-v5 episode (1000 steps); enlarge it",
        ),
        ("qprop_ppo", ["--twin-critic"], UNRECOGNIZED.format("--twin-critic")),  # the recipe's
        ("qprop_ppo", ["--kl-early-stop", "0"], "--kl-early-stop must be positive, got 0.0"),
        ("ipg_her", ["--nu", "1.5"], "--nu must be in [0, 1], got 1.5"),
        ("ipg_her", ["--tau", "0"], "--tau must be in (0, 1], got 0.0"),
        ("ipg_her", ["--gae-lambda", "1.1"], "--gae-lambda must be in [0, 1], got 1.1"),
        (
            "ipg_her",
            ["--her-goal-selection-strategy", "foo"],
            "--her-goal-selection-strategy expects one of (future, final, episode), got 'foo'",
        ),
        ("ipg_her", ["--her-n-sampled-goal", "-1"], "--her-n-sampled-goal must be non-negative, got -1"),
        ("ipg_her", ["--off-policy-batch-size", "0"], "--off-policy-batch-size must be positive, got 0"),
        ("ipg_her", ["--env-id", "Hopper-v5", "--her"], f"--her {NOT_A_GOAL_TASK}"),
        ("ipg_her", ["--env-id", "Hopper-v5", "--her-n-sampled-goal", "2"], f"--her-n-sampled-goal {NOT_A_GOAL_TASK}"),
        (
            "ipg_her",
            ["--no-her", "--her-n-sampled-goal", "2"],
            "--her-n-sampled-goal would be ignored (--no-her): leave it out",
        ),
        (
            "ipg_her",
            ["--no-her", "--her-goal-selection-strategy=final"],
            "--her-goal-selection-strategy would be ignored (--no-her): leave it out",
        ),
        (
            "ipg_her",
            ["--off-policy-states", "batch", "--off-policy-batch-size", "64"],
            "--off-policy-batch-size would be ignored (--off-policy-states batch): leave it out",
        ),
        (
            "ipg_her",
            ["--buffer-size", "10"],
            "--buffer-size 10 keeps 5 steps per env, less than one FetchReach-v4 episode (50 steps); enlarge it",
        ),
        ("ipg_her", ["--hidden", "0"], "--hidden must be positive, got 0"),
        (
            "ipg_her",
            ["--gamma", "1"],
            "--gamma 1.0 on a goal task: its returns are bounded by 1 / (1 - gamma), which needs gamma < 1 (e.g. 0.98)",
        ),
        (
            "ipg_her_recipe",
            ["--gamma", "1"],
            "--gamma 1.0 on a goal task: its returns are bounded by 1 / (1 - gamma), which needs gamma < 1 (e.g. 0.98)",
        ),
        ("ipg_her", ["--critic-steps", "-1"], "--critic-steps must be non-negative, got -1"),
        ("ipg_her", ["--learning-starts", "-1"], "--learning-starts must be non-negative, got -1"),
        ("ipg_her", ["--target-std", "1"], UNRECOGNIZED.format("--target-std, 1")),  # the recipe's
        ("ipg_her", ["--kl-early-stop", "-1"], "--kl-early-stop must be positive, got -1.0"),
        ("ipg_her_recipe", ["--kl-early-stop", "0"], "--kl-early-stop must be positive, got 0.0"),
        ("ppo_kl", ["--kl-early-stop", "0"], "--kl-early-stop must be positive, got 0.0"),
        ("ipg_her_recipe", ["--nu", "1.5"], "--nu must be in [0, 1], got 1.5"),
        ("ipg_her_recipe", ["--her-n-sampled-goal", "-1"], "--her-n-sampled-goal must be non-negative, got -1"),
        (
            "ipg_her_recipe",
            ["--buffer-size", "10"],
            "--buffer-size 10 keeps 5 steps per env, less than one FetchReach-v4 episode (50 steps); enlarge it",
        ),
        ("ipg_her_recipe", ["--nu", "0", "--action-l2", "1"], f"--action-l2 {NU_0}"),
        ("ipg_her_recipe", ["--nu", "0", "--twin-critic"], f"--twin-critic {NU_0}"),
        ("ipg_her_recipe", ["--nu", "0", "--bounds-loss", "1"], f"--bounds-loss {NU_0}"),
        ("ipg_her_recipe", ["--action-l2", "-1"], "--action-l2 must be non-negative, got -1.0"),
        ("ipg_her_recipe", ["--bounds-loss", "-1"], "--bounds-loss must be non-negative, got -1.0"),
        ("ipg_her_recipe", ["--target-std", "0"], "--target-std must be positive, got 0.0"),
        ("ipg_her_recipe", ["--target-std", "1", "-1", "1", "1"], "--target-std must be positive, got 1.0 -1.0 1.0 1.0"),
        (
            "ipg_her_recipe",
            ["--target-std", "1", "0.3"],
            "--target-std takes one sigma or one per action dimension (4 on FetchReach-v4), not 2",
        ),
        (
            "ipg_her_recipe",
            ["--target-std"],
            "--target-std takes one sigma or one per action dimension (4 on FetchReach-v4), not 0",
        ),
        ("ipg_her_recipe", ["--grasped-start", "1.5"], "--grasped-start must be in [0, 1], got 1.5"),
    ],
)
def test_algorithm_checks(capsys, script, argv, line):
    assert refused(capsys, SCRIPTS[script], *argv) == f"error: {line}"


RECIPE_ONLY = sorted(
    {f.name for f in dataclasses.fields(ipg_her_recipe.Args)} - {f.name for f in dataclasses.fields(ipg_her.Args)}
)
TINY_PPO = "--num-envs 2 --num-steps 128 --num-minibatches 2 --update-epochs 1 --eval-freq 0 --eval-episodes 1".split()


def test_the_recipes_flags_are_not_the_papers(capsys):
    """ipg_her.py is the paper's IPG+HER: each flag of the recipe is an unrecognized option
    there (and the recipe is ipg_her.py's flags plus its own)."""
    assert RECIPE_ONLY == [
        "action_l2",
        "bounds_loss",
        "grasped_start",
        "target_std",
        "target_std_decay",
        "target_std_decay_steps",
        "target_std_floor",
        "twin_critic",
    ]
    papers = {f.name: f.default for f in dataclasses.fields(ipg_her.Args)}
    recipes = {f.name: f.default for f in dataclasses.fields(ipg_her_recipe.Args)}
    changed = {name for name in papers if papers[name] != recipes[name]}
    assert changed == {"anneal_lr", "gamma", "hidden", "normalization"}  # the recipe's own defaults, in its --help
    assert not hasattr(ipg_her, "fill_in") and not hasattr(ipg_her, "sigma_rule")
    for name in RECIPE_ONLY:
        line = refused(capsys, ipg_her, cli.flag(name))
        assert line.startswith(f"error: unrecognized option {cli.flag(name)}"), line


@pytest.mark.parametrize("env_id", ["FetchPush-v4", "FetchPickAndPlace-v4", "FetchSlide-v4"])
def test_ipg_her_runs_a_hard_fetch_task_as_it_is_and_says_nothing_of_other_scripts(capsys, env_id):
    """The paper's algorithm runs the hard tasks with its own defaults (no task's), and its output
    names no other script or task: where the recipe wins and loses is the docs' to say."""
    args = parse(ipg_her, "--env-id", env_id)
    assert capsys.readouterr().out == ""
    assert vars(args) == vars(ipg_her.Args(env_id=env_id))  # no task defaults taken


@pytest.mark.parametrize("script", SCRIPTS)
def test_defaults_pass_the_checks(capsys, script):
    """The command with no flag runs what its Args say: every check takes the defaults (a refusal
    is one error line), and the run gets them as they are, the recipe its task's on top."""
    module = SCRIPTS[script]
    try:
        args = parse(module)
    except SystemExit:
        pytest.fail(f"the defaults are refused: {capsys.readouterr().err.strip()}")
    filled = module.fill_in(module.Args()) if hasattr(module, "fill_in") else {}
    assert vars(args) == vars(module.Args()) | filled


@pytest.mark.parametrize("module", [ipg_her, ipg_her_recipe], ids=["ipg_her", "ipg_her_recipe"])
@pytest.mark.parametrize("env_id", ["Hopper-v5", "FetchPush-v4"])
def test_checks_do_not_modify_args(module, env_id):
    args = cli.parse_args(module.Args, ["--env-id", env_id])
    before = vars(args).copy()
    module.check_args(args, ["--env-id", env_id])
    assert vars(args) == before


@pytest.mark.parametrize("script", ["qprop_ppo", "ipg_her", "ipg_her_recipe"])
def test_critic_learning_rate_must_be_positive(capsys, script):
    line = refused(capsys, SCRIPTS[script], "--critic-learning-rate", "-1")
    assert line == "error: --critic-learning-rate must be positive, got -1.0"


@pytest.mark.parametrize(
    "script, argv, needle",
    [
        ("qprop_ppo", ["--buffer-size", "100000000000"], "--buffer-size 100000000000 needs about "),
        ("ipg_her", ["--buffer-size", "100000000000"], "--buffer-size 100000000000 needs about "),
    ],
)
def test_a_buffer_larger_than_the_memory_is_refused(capsys, script, argv, needle):
    line = refused(capsys, SCRIPTS[script], *argv)
    assert needle in line and line.endswith("GiB are available; make it smaller"), line


def test_check_memory_refuses_what_the_machine_cannot_hold(capsys):
    cli.check_memory(tasks.available_memory() / 2, "--hidden 64")
    with pytest.raises(SystemExit):
        cli.check_memory(2 * tasks.available_memory(), "--hidden 100000")
    line = capsys.readouterr().err
    assert line.startswith("error: --hidden 100000 needs about ") and "are available" in line


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
    flags = (
        "--env-id",
        "Hopper-v5",
        "--total-timesteps",
        "700",
        *TINY_PPO,
    )
    result = run_script("ppo_kl.py", tmp_path, *flags)
    assert result.returncode == 0, result.stderr
    assert "--total-timesteps 700: 512 steps, whole batches of 256" in result.stdout
    assert "evaluation of step 512 (mean policy): eval_return=" in result.stdout


def test_a_renderer_that_cannot_load_is_refused_before_training(tmp_path):
    """MuJoCo loads MUJOCO_GL's renderer on import (osmesa without libosmesa6 raised a 38-line
    traceback even for plain training); an unknown one takes the same path."""
    env = {**os.environ, "MUJOCO_GL": "no-such-renderer"}
    result = subprocess.run(
        [sys.executable, str(ROOT / "ppo_kl.py"), "--log-dir", str(tmp_path)],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert_clean_error(result, "MUJOCO_GL=no-such-renderer", "unset MUJOCO_GL")
    assert not tmp_path.exists() or not run_dirs(tmp_path)


@pytest.mark.parametrize("script", SCRIPTS)
def test_no_flags_help_breaks_mid_sentence(script):
    """tyro keeps a field docstring's line breaks in --help, where the terminal's wrapping need not fall: each field's
    help is one line of source (the fields of common/'s argument classes too)."""
    from tyro import _docstrings

    args = SCRIPTS[script].Args
    broken = [f.name for f in dataclasses.fields(args) if "\n" in (_docstrings.get_field_docstring(args, f.name, ()) or "")]
    assert not broken, f"{script}.py --help breaks these fields' help mid-sentence: {broken}"


def test_what_follows_from_the_task_is_filled_in_where_help_says_none_and_a_flag_given_wins():
    """ipg_her_recipe.py's defaults are its Args' (its --help); three fields default to None, "filled in at start" by
    ``fill_in`` from the task, one rule for every task and no row for any: sigma min(1, 2 / sqrt(d)) on each of d action
    dimensions, gamma 1 - 1/H for H-step episodes (at most 0.995), grasped starts where the gripper can hold the object.
    A flag given wins; nothing else changes."""
    nones = {f.name for f in dataclasses.fields(ipg_her_recipe.Args) if f.default is None}
    papers = {f.name for f in dataclasses.fields(ipg_her.Args) if f.default is None}
    assert nones - papers == {"gamma", "target_std", "grasped_start"}
    help_text = " ".join(
        subprocess.run([sys.executable, str(ROOT / "ipg_her_recipe.py"), "--help"], capture_output=True, text=True)
        .stdout.replace("│", " ")  # the box's border, between the lines of a wrapped help
        .split()
    )
    assert help_text.count("filled in at start) (default: None)") == 3  # each of the three says so in --help
    own = {  # d action dimensions, H steps an episode, whether the object can be held
        "FetchReach-v4": ((1.0,) * 4, 0.98, 0.0),
        "FetchPickAndPlace-v4": ((1.0,) * 4, 0.98, 0.5),
        "FetchSlide-v4": ((1.0,) * 4, 0.98, 0.0),  # its gripper is blocked
        "HandReach-v3": ((0.447,) * 20, 0.98, 0.0),  # 2 / sqrt(20)
        "HandManipulateBlockRotateZ-v1": ((0.447,) * 20, 0.99, 0.0),  # 100 steps
        "PointMaze_Medium-v3": ((1.0, 1.0), 0.995, 0.0),  # 1 - 1/600, clipped
        "Hopper-v5": ((1.0,) * 3, 0.995, 0.0),  # the same rule on a task without goals
    }
    for env_id, (target_std, gamma, grasped_start) in own.items():
        args = ipg_her_recipe.Args(env_id=env_id)
        filled = ipg_her_recipe.fill_in(args)
        assert filled == dict(target_std=target_std, gamma=gamma, grasped_start=grasped_start), env_id
        assert vars(args) == vars(ipg_her_recipe.Args(env_id=env_id)) | filled
    given = ipg_her_recipe.Args(env_id="FetchPickAndPlace-v4", gamma=0.95, target_std=0.3, grasped_start=0.0)
    assert ipg_her_recipe.fill_in(given) == {} and (given.gamma, given.target_std, given.grasped_start) == (0.95, 0.3, 0.0)
    assert cli.spelled({"target_std": (1.0, 0.3), "twin_critic": True, "gamma": 0.98}) == (
        "--target-std 1.0 0.3, --twin-critic, --gamma 0.98"
    )  # the line the script prints, as one would type it


def test_the_script_prints_what_it_filled_in(tmp_path):
    """The main section prints the task's values it filled in, as one would type them, before the run."""
    flags = ("--env-id", "FetchPush-v4", "--gamma", "0.95", "--total-timesteps", "100", "--eval-freq", "0")
    result = run_script("ipg_her_recipe.py", tmp_path, *flags, "--learning-starts", "0", "--critic-steps", "1")
    assert result.returncode == 0, result.stderr
    assert "filled in from FetchPush-v4: --target-std 1.0 1.0 1.0 1.0, --grasped-start 0.0\n" in result.stdout


IPG = {"ipg_her": ipg_her, "ipg_her_recipe": ipg_her_recipe}  # the recipe keeps IPG's checks


PUSH = ("--env-id", "FetchPush-v4")


# row 9: a flag given wins over the task's default, whatever its spelling
@pytest.mark.parametrize(
    "argv, field, value",
    [
        (["--target_std 0.5"], "target_std", 0.5),
        (["--target_std=0.5", "--target-std=0.5"], "target_std", 0.5),  # and as tyro spells it
        (["--no_twin_critic"], "twin_critic", False),
        (["--no-twin_critic", "--no-twin-critic"], "twin_critic", False),
        (["--action_l2=0.5", "--action-l2=0.5"], "action_l2", 0.5),
    ],
)
def test_a_flag_given_in_any_spelling_beats_the_tasks_default(capsys, argv, field, value):
    for typed in argv:
        args = parse(ipg_her_recipe, *PUSH, *typed.split())
        assert getattr(args, field) == value
        assert ipg_her_recipe.fill_in(args) == {}  # nothing left to fill in


@pytest.mark.parametrize("typed", ["--twin_critic", "--no-twin-critic", "--no_twin_critic", "--no-twin_critic"])
def test_an_ignored_boolean_is_refused_whatever_its_spelling(capsys, typed):
    line = refused(capsys, ipg_her_recipe, "--nu", "0", typed)
    assert line.startswith(f"error: {typed} would be ignored (at --nu 0 without --use-cv")


@pytest.mark.parametrize("argv", [["--action_l2=1"], ["--action_l2", "1"], ["--bounds_loss=1"]])
def test_an_ignored_value_flag_is_refused_whatever_its_spelling(capsys, argv):
    assert "would be ignored" in refused(capsys, ipg_her_recipe, "--nu", "0", *argv)


def test_ignored_gathers_the_rules_that_hold_and_a_later_rule_wins():
    """``cli.ignored``: ``{flag: why}`` of every flag of every rule whose condition holds; a rule
    that does not hold adds nothing, and a flag in two rules takes the later one's why."""
    assert cli.ignored() == {}
    assert cli.ignored((False, "--a --b", "never")) == {}
    assert cli.ignored((True, "--a --b", "first"), (False, "--c", "never")) == {"--a": "first", "--b": "first"}
    assert cli.ignored((True, "--a --b", "first"), (True, "--b --c", "later")) == {
        "--a": "first",
        "--b": "later",
        "--c": "later",
    }
    assert cli.ignored((True, "--b", "first"), (False, "--b", "never")) == {"--b": "first"}


def test_refuse_ignored_reads_every_spelling(capsys):
    for typed in ("--a-b", "--a_b", "--a-b=1", "--a_b=x", "--no-a-b", "--no_a_b", "--no-a_b"):
        with pytest.raises(SystemExit):
            cli.refuse_ignored(["--x", "1", typed], {"--a-b": "why"})
        line = f"error: {typed.split('=')[0]} would be ignored (why): leave it out\n"
        assert capsys.readouterr().err == line  # as typed
    cli.refuse_ignored(["--a-bc", "--nu", "--norm-adv"], {"--a-b": "why", "--u": "why"})


# row 10: what IPG ignores at nu = 0 without the control variate, and at nu = 1 with it
NU0_IGNORED = [
    ["--q-bar", "sample"],
    ["--off-policy-states", "replay"],
    ["--off-policy-batch-size", "64"],
    ["--normalization", "paper"],
    ["--tau", "0.1"],
    ["--critic-steps", "10"],
    ["--critic-learning-rate", "1e-4"],
    ["--critic-batch-size", "64"],
    ["--buffer-size", "100000"],
    ["--learning-starts", "0"],
    ["--diagnostics-every", "1"],
    ["--her-n-sampled-goal", "2"],
    ["--her-goal-selection-strategy", "final"],
    ["--her"],
    ["--no-her"],
]
RECIPE_NU0_IGNORED = [  # the recipe's critic flags, and its penalties on the off-policy term
    ["--twin-critic"],
    ["--action-l2", "1"],
    ["--bounds-loss", "1"],
]


@pytest.mark.parametrize(
    "script, argv",
    [(script, argv) for script in IPG for argv in NU0_IGNORED] + [("ipg_her_recipe", argv) for argv in RECIPE_NU0_IGNORED],
)
def test_at_nu_0_without_control_variate_the_critics_flags_are_refused(capsys, script, argv):
    line = refused(capsys, IPG[script], "--nu", "0", *argv)
    assert line == f"error: {argv[0]} would be ignored (at --nu 0 without --use-cv no term uses the critic): leave it out"
    parse(IPG[script], "--nu", "0", "--use-cv", *argv)  # with the control variate they count
    parse(IPG[script], "--nu", "0.5", *argv)  # and in the middle


@pytest.mark.parametrize("script", IPG)
@pytest.mark.parametrize(
    "argv, line",
    [
        (
            ["--her-n-sampled-goal", "0", "--her-goal-selection-strategy", "final"],
            "--her-goal-selection-strategy would be ignored (--her-n-sampled-goal 0 relabels no goal)",
        ),
        (["--nu", "1", "--use-cv"], "--use-cv would be ignored (at --nu 1 its on-policy term has weight 0)"),
        (["--use-cv"], "--use-cv would be ignored (at --nu 1 its on-policy term has weight 0)"),
        (
            ["--no-norm-adv", "--normalization", "paper"],
            "--normalization would be ignored (--no-norm-adv: nothing to normalise)",
        ),
        (
            ["--off-policy-states", "batch", "--off-policy-batch-size", "64"],
            "--off-policy-batch-size would be ignored (--off-policy-states batch)",
        ),
        (
            ["--env-id", "Hopper-v5", "--her-goal-selection-strategy", "final"],
            "--her-goal-selection-strategy would be ignored (Hopper-v5 is not a goal task)",
        ),
    ],
)
def test_other_ignored_ipg_combinations_are_refused(capsys, script, argv, line):
    assert refused(capsys, IPG[script], *argv) == f"error: {line}: leave it out"


@pytest.mark.parametrize(
    "argv",
    [
        ["--tau", "0.1"],
        ["--critic-steps", "1"],
        ["--buffer-size", "5000"],
        ["--learning-starts", "0"],
        ["--critic-hidden", "64"],
        ["--normalization", "paper"],
        ["--critic_learning_rate=1e-4"],
    ],
)
def test_qprop_without_a_critic_refuses_the_critics_flags(capsys, argv):
    line = refused(capsys, qprop_ppo, "--eta-mode", "none", *argv)
    assert line.startswith(f"error: {argv[0].split('=')[0]} would be ignored (--eta-mode none")
    parse(qprop_ppo, *argv)


def test_qprop_without_advantage_normalisation_refuses_a_normalization_mode(capsys):
    line = refused(capsys, qprop_ppo, "--no-norm-adv", "--normalization", "paper")
    assert line.startswith("error: --normalization would be ignored (--no-norm-adv")


def test_nu_0_trains_no_critic_and_a_task_without_goals_says_hindsight_is_off(tmp_path):
    """At nu = 0 without control variate nothing uses the critic: it does not train and the
    ipg/* diagnostics, which need it, are not measured; Hopper has no goals: one line says that
    hindsight relabelling is off, before training."""
    flags = (
        "--env-id",
        "Hopper-v5",
        "--nu",
        "0",
        "--total-timesteps",
        "512",
        *TINY_PPO,
        "--eval-workers",
        "0",
    )
    result = run_script("ipg_her.py", tmp_path, *flags)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0] == "Hopper-v5 has no goals: hindsight relabelling (HER) is off"
    assert lines[1].startswith("run folder: ")
    (run_dir,) = run_dirs(tmp_path)
    tags = scalars(run_dir)
    assert "losses/policy_loss" in tags and len(tags["losses/policy_loss"]) == 2
    assert not {"losses/critic_loss", "losses/q_values", "ipg/grad_var", "ipg/effective_nu"} & set(tags)


# rows 14/15: nan and inf in any float flag
def float_fields(args_class) -> list[str]:
    hints = typing.get_type_hints(args_class)
    return [name for name, hint in hints.items() if "float" in str(hint) or hint is float]


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
@pytest.mark.parametrize("script", SCRIPTS)
def test_every_float_flag_refuses_nan_and_inf(capsys, script, value):
    names = float_fields(SCRIPTS[script].Args)
    assert {"learning_rate", "beta_init", "kl_target"} <= set(names)
    assert "kl_early_stop" in names  # in all four: DPPO's early stop of the epochs
    assert ("target_std" in names) == (script == "ipg_her_recipe")  # a tuple or None
    for name in names:
        line = refused(capsys, SCRIPTS[script], cli.flag(name), value)
        assert line == f"error: {cli.flag(name)} must be a finite number, got {float(value)}"


def test_a_tuple_of_floats_refuses_nan_and_none_stays_allowed(capsys):
    line = refused(capsys, ipg_her_recipe, "--target-std", "1", "nan", "1", "1")
    assert line == "error: --target-std must be a finite number, got 1.0 nan 1.0 1.0"
    assert parse(ppo_kl, "--kl-early-stop", "None").kl_early_stop is None
    assert parse(ipg_her_recipe, "--target-std", "None").target_std == (1.0,) * 4  # None: filled in from the task


@pytest.mark.parametrize(
    "script, argv, needle",
    [
        ("ppo_kl", ["--learning-rate", "nan"], "--learning-rate must be a finite number, got nan"),
        ("qprop_ppo", ["--beta-init", "inf"], "--beta-init must be a finite number, got inf"),
        ("ipg_her", ["--nu", "0", "--tau", "0.1"], "--tau would be ignored"),
        ("ipg_her", ["--gamma", "1"], "--gamma 1.0 on a goal task"),
        ("ipg_her_recipe", ["--gamma", "1"], "--gamma 1.0 on a goal task"),
        ("ppo_kl", ["--torch-threads", "0"], "--torch-threads must be positive"),
        ("ppo_kl", ["--exp-name", "../../x"], "--exp-name '../../x' must be a plain name"),
        ("ipg_her", ["--hidden", "100000"], "--hidden 100000 with batches of 256"),
        ("ipg_her_recipe", ["--off-policy-batch-size", "1000000000"], "batches of 1,000,000,000"),
        ("qprop_ppo", ["--critic-hidden", "200000"], "--critic-hidden 200000 with"),
    ],
)
def test_refusals_end_to_end_leave_no_run_folder(tmp_path, script, argv, needle):
    result = run_script(f"{script}.py", tmp_path, *argv, timeout=120)
    assert_clean_error(result, needle)
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr  # that line alone
    assert not (tmp_path.exists() and run_dirs(tmp_path)), "no run folder for rejected input"


# row 17: tyro's parse errors, one line each: what the flag expects, what it got
@pytest.mark.parametrize(
    "script, argv, line",
    [
        ("ppo_kl", ["--total-timesteps", "1e5"], "--total-timesteps expects an integer, got '1e5'"),
        ("ppo_kl", ["--seed", "1.5"], "--seed expects an integer, got '1.5'"),
        ("ppo_kl", ["--seed=x"], "--seed expects an integer, got 'x'"),
        ("qprop_ppo", ["--gamma", "high"], "--gamma expects a number, got 'high'"),
        ("ppo_kl", ["--kl-early-stop", "x"], "--kl-early-stop expects a number or None, got 'x'"),
        ("ipg_her_recipe", ["--target-std", "1", "x"], "--target-std expects None, a number or several, got '1 x'"),
        ("ipg_her", ["--q-bar", "foo"], "--q-bar expects one of (mean, sample), got 'foo'"),
        (
            "ipg_her",
            ["--her_goal_selection_strategy=best"],
            "--her-goal-selection-strategy expects one of (future, final, episode), got 'best'",
        ),
        (
            "qprop_ppo",
            ["--eta-mode", "x"],
            "--eta-mode expects one of (batch-conservative, batch-aggressive, conservative, aggressive, ones, none), got 'x'",
        ),
        ("ppo_kl", ["--env-id"], "--env-id expects a value"),
    ],
)
def test_a_parse_error_is_one_line_saying_what_the_flag_expects(capsys, script, argv, line):
    assert refused(capsys, SCRIPTS[script], *argv) == f"error: {line}"


# row 18: one flag and its value per error (test_cli.py's test_algorithm_checks); an old task
# version's current one
@pytest.mark.parametrize("old, current", [("FetchReach-v1", "FetchReach-v4"), ("FetchPush-v1", "FetchPush-v4")])
def test_an_old_task_version_suggests_the_current_one(capsys, old, current):
    """A mujoco-py task: its name's highest version that constructs, not an unrelated one."""
    line = refused(capsys, ppo_kl, "--env-id", old)
    assert line.endswith(f"not support; use {current}") and "Hopper" not in line, line
    assert refused(capsys, ppo_kl, "--env-id", "Hopper-v2").endswith("use Hopper-v5")
    assert refused(capsys, ppo_kl, "--env-id", "FetchReach-v9").endswith("FetchReach-v4?")


def test_a_task_of_a_users_module_is_imported_first_and_a_missing_one_refused(tmp_path, capsys):
    """gymnasium's ``module:Task-v0``: the module registers the task (docs/your_goal_task.md), so
    it is imported before the id is looked up; in a fresh process only that import registers it."""
    result = run_script("ipg_her.py", tmp_path, "--env-id", "tests.point_goal:PointGoal-v9")
    assert_clean_error(result, "unknown --env-id 'tests.point_goal:PointGoal-v9'; did you mean tests.point_goal:PointGoal-v0?")
    assert parse(ipg_her, "--env-id", "tests.point_goal:PointGoal-v0").env_id.endswith(":PointGoal-v0")
    line = refused(capsys, ipg_her, "--env-id", "no_such_module:PointGoal-v0")
    assert "cannot import no_such_module (ModuleNotFoundError" in line, line


def test_a_task_without_a_time_limit_or_with_goals_not_vectors_is_refused(capsys):
    """Replay and evaluation wait for episodes to end; a goal must be a vector (goal_dim)."""
    from tests.point_goal import PointGoal

    class MatrixGoal(PointGoal):
        def __init__(self):
            super().__init__()
            box = gym.spaces.Box(-1.0, 1.0, (2, 2), np.float64)
            self.observation_space = gym.spaces.Dict({"observation": box, "achieved_goal": box, "desired_goal": box})

    for env_id, entry, limit in (("PointGoalForever-v0", PointGoal, None), ("MatrixGoal-v0", MatrixGoal, 50)):
        if env_id not in gym.registry:
            gym.register(env_id, entry_point=entry, max_episode_steps=limit)
    line = refused(capsys, ipg_her, "--env-id", "PointGoalForever-v0")
    assert line == (
        "error: PointGoalForever-v0 has no time limit: register it with max_episode_steps, so that its episodes end"
    )
    line = refused(capsys, ipg_her, "--env-id", "MatrixGoal-v0")
    assert line.startswith("error: MatrixGoal-v0's observations are not supported"), line


def test_a_goal_task_whose_observations_are_not_its_declared_space_is_refused(capsys):
    """One reset in the checks, before the run folder exists: a goal 3 long where the space
    declares 2 would fail deep in the vector env (``Output array is the wrong shape``)."""
    from tests.point_goal import PointGoal

    class WrongGoal(PointGoal):
        def _obs(self):
            return super()._obs() | {"desired_goal": np.zeros(3)}

    if "WrongGoal-v0" not in gym.registry:
        gym.register("WrongGoal-v0", entry_point=WrongGoal, max_episode_steps=50)
    assert refused(capsys, ipg_her, "--env-id", "WrongGoal-v0") == (
        "error: WrongGoal-v0's reset returns an observation 'desired_goal' of shape (3,), its "
        "observation space declares (2,): make them agree"
    )


def test_capture_video_on_a_task_that_renders_no_frames_says_so(capsys):
    line = refused(capsys, ipg_her, "--env-id", "tests.point_goal:PointGoal-v0", "--capture-video")
    assert line == ("error: --capture-video: tests.point_goal:PointGoal-v0 renders no rgb_array frames (render_modes [])")


# row 19: a task without goals trains without HER, and says so
@pytest.mark.parametrize("script", IPG)
def test_ipg_on_a_task_without_goals_says_hindsight_is_off(capsys, script):
    parse(IPG[script], "--env-id", "Hopper-v5")
    assert capsys.readouterr().out == "Hopper-v5 has no goals: hindsight relabelling (HER) is off\n"
    parse(IPG[script], "--env-id", "FetchReach-v4")
    assert capsys.readouterr().out == ""


def test_parsing_hands_ctrl_c_back_to_python_once_the_libraries_are_loaded():
    """While a script's libraries load, Ctrl-C ends it at once (``interrupted_while_loading``);
    from ``parse_args`` on it is a KeyboardInterrupt again, so an evaluation or a run unwinds (its
    files closed, its workers ended) instead of vanishing."""
    import signal

    @dataclasses.dataclass
    class Args:
        env_id: str = "FetchReach-v4"

    previous = signal.signal(signal.SIGINT, cli.interrupted_while_loading)
    try:
        cli.parse_args(Args, [])
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)
