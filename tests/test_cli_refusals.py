"""Bad input the scripts once accepted, or refused with a line that named the wrong thing: flags
in any spelling, flags a run would ignore (IPG at nu = 0 and 1, Q-Prop without a critic), nan
and inf, tyro's parse errors, and one error per flag. In-process, plus a few runs as a user
runs them (one line, no run folder)."""

import typing

import pytest
from conftest import assert_clean_error, run_dirs, run_script, scalars

import ipg_her
import ppo_kl
import qprop_ppo
from common import cli

SCRIPTS = {"ppo_kl": ppo_kl, "qprop_ppo": qprop_ppo, "ipg_her": ipg_her}


def parse(script, *argv: str):
    """Parse and check ``argv`` as ``script``'s ``__main__`` does (ipg_her.py: its task
    defaults, less the ones the run would ignore)."""
    module, argv = SCRIPTS[script], list(argv)
    if module is ipg_her:
        args = cli.parse_args(ipg_her.Args, argv, task_defaults=ipg_her.TASK_DEFAULTS,
                              ignored=cli.ipg_ignored)  # fmt: skip
    else:
        args = cli.parse_args(module.Args, argv)
    module.check_args(args) if module is ppo_kl else module.check_args(args, argv)
    return args


def refused(capsys, script, *argv: str) -> str:
    """The one ``error:`` line (exit 2) that ``argv`` is refused with."""
    with pytest.raises(SystemExit) as exit_info:
        parse(script, *argv)
    assert exit_info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0]


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
        args = parse("ipg_her", *PUSH, *typed.split())
        assert getattr(args, field) == value
        line = capsys.readouterr().out.strip().splitlines()[0]
        assert line.startswith("FetchPush-v4's own defaults: --hidden 256, ")
        assert cli.flag(field) not in line  # not called the task's own


@pytest.mark.parametrize(
    "typed", ["--twin_critic", "--no-twin-critic", "--no_twin_critic", "--no-twin_critic"]
)
def test_an_ignored_boolean_is_refused_whatever_its_spelling(capsys, typed):
    line = refused(capsys, "ipg_her", "--nu", "0", typed)
    assert line.startswith(f"error: {typed} would be ignored (at --nu 0 without --use-cv")


@pytest.mark.parametrize(
    "argv", [["--critic_target=sample"], ["--action_l2", "1"], ["--bounds_loss=1"]]
)
def test_an_ignored_value_flag_is_refused_whatever_its_spelling(capsys, argv):
    assert "would be ignored" in refused(capsys, "ipg_her", "--nu", "0", *argv)


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
    ["--critic-target", "sample"],
    ["--clip-q-target"],
    ["--no-clip-q-target"],
    ["--buffer-size", "100000"],
    ["--learning-starts", "0"],
    ["--twin-critic"],
    ["--action-l2", "1"],
    ["--bounds-loss", "1"],
    ["--diagnostics-every", "1"],
    ["--her-n-sampled-goal", "2"],
    ["--no-her"],
]


@pytest.mark.parametrize("argv", NU0_IGNORED)
def test_at_nu_0_without_control_variate_the_critics_flags_are_refused(capsys, argv):
    line = refused(capsys, "ipg_her", "--nu", "0", *argv)
    assert line == f"error: {argv[0]} would be ignored (at --nu 0 without --use-cv no term uses " \
                   "the critic): leave it out"  # fmt: skip
    parse("ipg_her", "--nu", "0", "--use-cv", *argv)  # with the control variate they count
    parse("ipg_her", "--nu", "0.5", *argv)  # and in the middle


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--her-n-sampled-goal", "0", "--her-goal-selection-strategy", "final"],
         "error: --her-goal-selection-strategy would be ignored (--her-n-sampled-goal 0"),
        (["--nu", "1", "--use-cv"], "error: --use-cv would be ignored (at --nu 1"),
        (["--use-cv"], "error: --use-cv would be ignored (at --nu 1"),
        (["--no-norm-adv", "--normalization", "paper"], "error: --normalization would be ignored"),
        (["--env-id", "Hopper-v5", "--no-clip-q-target"],
         "error: --no-clip-q-target would be ignored (Hopper-v5 is not a goal task)"),
    ],
)  # fmt: skip
def test_other_ignored_ipg_combinations_are_refused(capsys, argv, needle):
    assert refused(capsys, "ipg_her", *argv).startswith(needle)


@pytest.mark.parametrize(
    "argv", [["--tau", "0.1"], ["--critic-steps", "1"], ["--buffer-size", "5000"],
             ["--learning-starts", "0"], ["--critic-hidden", "64"], ["--normalization", "paper"],
             ["--critic_learning_rate=1e-4"], ["--twin-critic"]],
)  # fmt: skip
def test_qprop_without_a_critic_refuses_the_critics_flags(capsys, argv):
    line = refused(capsys, "qprop_ppo", "--eta-mode", "none", *argv)
    assert line.startswith(f"error: {argv[0].split('=')[0]} would be ignored (--eta-mode none")
    parse("qprop_ppo", *argv)


def test_qprop_without_advantage_normalisation_refuses_a_normalization_mode(capsys):
    line = refused(capsys, "qprop_ppo", "--no-norm-adv", "--normalization", "paper")
    assert line.startswith("error: --normalization would be ignored (--no-norm-adv")


def test_task_defaults_the_run_would_ignore_are_neither_applied_nor_printed(capsys):
    args = parse("ipg_her", *PUSH, "--nu", "0")
    assert (
        capsys.readouterr().out == "FetchPush-v4's own defaults: --hidden 256, --target-std 1.0\n"
    )
    assert (args.twin_critic, args.action_l2, args.normalization) == (False, 0.0, "unbiased")
    assert (args.hidden, args.target_std) == (256, 1.0)  # the policy's: applied
    args = parse("ipg_her", *PUSH, "--nu", "0", "--use-cv")  # the critic counts again
    assert "--action-l2 1.0, --twin-critic" in capsys.readouterr().out
    assert args.twin_critic and args.action_l2 == 1.0


def test_nu_0_trains_no_critic_and_a_task_without_goals_says_hindsight_is_off(tmp_path):
    """At nu = 0 without control variate nothing uses the critic: it does not train and the
    ipg/* diagnostics, which need it, are not measured; Hopper has no goals: one line says that
    hindsight relabelling is off, before training."""
    flags = ("--env-id", "Hopper-v5", "--nu", "0", "--total-timesteps", "512", "--num-envs",
             "2", "--num-steps", "128", "--num-minibatches", "2", "--update-epochs", "1",
             "--eval-freq", "0", "--eval-episodes", "1", "--eval-workers", "0")  # fmt: skip
    result = run_script("ipg_her.py", tmp_path, *flags)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0] == "Hopper-v5 has no goals: hindsight relabelling (HER) is off"
    assert lines[1].startswith("run folder: ")
    (run_dir,) = run_dirs(tmp_path)
    tags = scalars(run_dir)
    assert "losses/policy_loss" in tags and len(tags["losses/policy_loss"]) == 2
    assert not {"losses/critic_loss", "losses/q_values", "ipg/grad_var", "ipg/effective_nu"} & set(
        tags
    )


# rows 14/15: nan and inf in any float flag
def float_fields(args_class) -> list[str]:
    hints = typing.get_type_hints(args_class)
    return [name for name, hint in hints.items() if "float" in str(hint) or hint is float]


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
@pytest.mark.parametrize("script", SCRIPTS)
def test_every_float_flag_refuses_nan_and_inf(capsys, script, value):
    names = float_fields(SCRIPTS[script].Args)
    assert {"learning_rate", "beta_init", "kl_target", "kl_early_stop"} <= set(names)
    for name in names:
        line = refused(capsys, script, cli.flag(name), value)
        assert line == f"error: {cli.flag(name)} must be a finite number, got {float(value)}"


def test_a_tuple_of_floats_refuses_nan_and_none_stays_allowed(capsys):
    line = refused(capsys, "ipg_her", "--target-std", "1", "nan", "1", "1")
    assert line == "error: --target-std must be a finite number, got 1.0 nan 1.0 1.0"
    assert parse("ppo_kl", "--kl-early-stop", "None").kl_early_stop is None


@pytest.mark.parametrize(
    "script, argv, needle",
    [("ppo_kl", ["--learning-rate", "nan"], "--learning-rate must be a finite number, got nan"),
     ("qprop_ppo", ["--beta-init", "inf"], "--beta-init must be a finite number, got inf"),
     ("ipg_her", ["--nu", "0", "--tau", "0.1"], "--tau would be ignored")],
)  # fmt: skip
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
        ("ipg_her", ["--target-std", "1", "x"],
         "--target-std expects None, a number or several, got '1 x'"),
        ("ipg_her", ["--q-bar", "foo"], "--q-bar expects one of (mean, sample), got 'foo'"),
        ("ipg_her", ["--her_goal_selection_strategy=best"],
         "--her-goal-selection-strategy expects one of (future, final, episode), got 'best'"),
        ("qprop_ppo", ["--eta-mode", "x"], "--eta-mode expects one of (batch-conservative, "
         "batch-aggressive, conservative, aggressive, ones, none), got 'x'"),
        ("ppo_kl", ["--env-id"], "--env-id expects a value"),
    ],
)  # fmt: skip
def test_a_parse_error_is_one_line_saying_what_the_flag_expects(capsys, script, argv, line):
    assert refused(capsys, script, *argv) == f"error: {line}"


# row 18: one flag and its value per error; an old task version's current one
@pytest.mark.parametrize(
    "script, argv, line",
    [
        ("ipg_her", ["--nu", "1.5"], "--nu must be in [0, 1], got 1.5"),
        (
            "ipg_her",
            ["--her-n-sampled-goal", "-1"],
            "--her-n-sampled-goal must be non-negative, got -1",
        ),  # noqa: E501
        ("ppo_kl", ["--gamma", "1.5"], "--gamma must be in (0, 1], got 1.5"),
        ("qprop_ppo", ["--gamma", "0"], "--gamma must be in (0, 1], got 0.0"),
        ("ppo_kl", ["--gae-lambda", "-0.1"], "--gae-lambda must be in [0, 1], got -0.1"),
        ("ipg_her", ["--gae-lambda", "1.1"], "--gae-lambda must be in [0, 1], got 1.1"),
        ("ppo_kl", ["--kl-target", "0"], "--kl-target must be positive, got 0.0"),
        ("ppo_kl", ["--beta-init", "-1"], "--beta-init must be non-negative, got -1.0"),
        ("qprop_ppo", ["--critic-steps", "-1"], "--critic-steps must be non-negative, got -1"),
        ("ipg_her", ["--learning-starts", "-1"], "--learning-starts must be non-negative, got -1"),
        ("ipg_her", ["--action-l2", "-1"], "--action-l2 must be non-negative, got -1.0"),
        ("ipg_her", ["--target-std", "0"], "--target-std must be positive, got 0.0"),
        (
            "ipg_her",
            ["--target-std"],
            "--target-std takes one sigma or one per action dimension (4 on FetchReach-v4), not 0",
        ),  # a bare flag: an empty tuple
        ("ipg_her", ["--grasped-start", "1.5"], "--grasped-start must be in [0, 1], got 1.5"),
    ],
)
def test_a_range_error_names_only_its_flag_and_value(capsys, script, argv, line):
    assert refused(capsys, script, *argv) == f"error: {line}"


@pytest.mark.parametrize("old, current", [("FetchReach-v1", "FetchReach-v4"),
                                          ("FetchPush-v1", "FetchPush-v4")])  # fmt: skip
def test_an_old_task_version_suggests_the_current_one(capsys, old, current):
    """A mujoco-py task: its name's highest version that constructs, not an unrelated one."""
    line = refused(capsys, "ppo_kl", "--env-id", old)
    assert line.endswith(f"not support; use {current}") and "Hopper" not in line, line
    assert refused(capsys, "ppo_kl", "--env-id", "Hopper-v2").endswith("use Hopper-v5")
    assert refused(capsys, "ppo_kl", "--env-id", "FetchReach-v9").endswith("FetchReach-v4?")


# row 19: a task without goals trains without HER, and says so
def test_ipg_on_a_task_without_goals_says_hindsight_is_off(capsys):
    parse("ipg_her", "--env-id", "Hopper-v5")
    assert capsys.readouterr().out == "Hopper-v5 has no goals: hindsight relabelling (HER) is off\n"
    parse("ipg_her", "--env-id", "FetchReach-v4")
    assert capsys.readouterr().out == ""
