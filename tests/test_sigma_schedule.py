"""ipg_her_recipe.py's sigma rule towards targets that decay over training (``--target-std-decay``): the schedule is
geometric and then held, never below ``--target-std-floor``, 1 holds the targets as they were, and the training loop
steps the rule towards the decayed targets."""

import numpy as np
from conftest import run_dirs, run_script, scalars

import ipg_her_recipe


def test_the_targets_decay_geometrically_then_hold():
    targets = (1.0, 0.5)
    np.testing.assert_allclose(ipg_her_recipe.annealed(targets, 0.3, 0.0), targets)
    np.testing.assert_allclose(ipg_her_recipe.annealed(targets, 0.3, 0.5), np.array(targets) * 0.3**0.5)
    np.testing.assert_allclose(ipg_her_recipe.annealed(targets, 0.3, 1.0), np.array(targets) * 0.3)
    np.testing.assert_allclose(ipg_her_recipe.annealed(targets, 0.3, 7.0), np.array(targets) * 0.3)  # then held
    assert ipg_her_recipe.annealed(targets, 1.0, 0.5) is targets  # 1: the targets as given, the same numbers
    np.testing.assert_allclose(ipg_her_recipe.annealed(0.8, 0.5, 1.0), 0.4)  # one summed target too


def test_no_target_decays_below_the_floor_and_one_below_it_is_held():
    """--target-std-floor: the hand's 0.447 stops at 0.3 (not 0.134), a Fetch task's 1.0 reaches 0.3 as the decay takes
    it, a target given below the floor stays where it was given."""
    np.testing.assert_allclose(ipg_her_recipe.annealed((0.447,) * 2, 0.3, 1.0, 0.3), (0.3, 0.3))
    np.testing.assert_allclose(ipg_her_recipe.annealed((1.0, 0.2), 0.3, 1.0, 0.3), (0.3, 0.2))
    np.testing.assert_allclose(ipg_her_recipe.annealed((1.0, 0.2), 0.3, 0.5, 0.3), (0.3**0.5, 0.2))
    np.testing.assert_allclose(ipg_her_recipe.annealed((0.447,), 0.3, 1.0, 0.0), (0.447 * 0.3,))  # floor 0: none
    assert ipg_her_recipe.Args().target_std_floor == 0.3 and ipg_her_recipe.Args().target_std_decay == 0.3


def test_the_loop_steps_the_rule_towards_the_decayed_targets(tmp_path):
    """alpha moves by 0.01 (log target - log sigma) per update: with targets that fall to a hundredth within the first
    100 steps, the multiplier falls below the run's with held targets, from the same seed."""
    flags = ("--env-id", "FetchReach-v4", "--total-timesteps", "600", "--eval-freq", "0", "--critic-steps", "2")
    alphas = {}
    for decay in ("1.0", "0.01"):
        extra = ("--target-std-decay", decay, "--target-std-decay-steps", "100") if decay != "1.0" else ()
        result = run_script("ipg_her_recipe.py", tmp_path / decay, *flags, *extra)
        assert result.returncode == 0, result.stderr
        (run_dir,) = run_dirs(tmp_path / decay)
        alphas[decay] = [value for _, value in scalars(run_dir)["ipg/alpha"]]
    assert alphas["1.0"][0] == alphas["0.01"][0] == 0.0  # the first update, before any step of the rule
    assert alphas["0.01"][-1] < alphas["1.0"][-1] - 0.05  # log(0.01) = -4.6: each step lower by 0.046


def test_the_schedules_flags_are_refused_where_the_targets_are_held(capsys):
    """At --target-std-decay 1 the targets are held: its steps and its floor would be ignored, so each is refused with one
    line; a negative floor is refused too."""
    import pytest

    from common import cli

    for flags in (("--target-std-floor", "0.2"), ("--target-std-decay-steps", "50000")):
        argv = ["--target-std-decay", "1", *flags]
        with pytest.raises(SystemExit):
            ipg_her_recipe.check_args(cli.parse_args(ipg_her_recipe.Args, argv), argv)
        assert (
            capsys.readouterr().err
            == f"error: {flags[0]} would be ignored (--target-std-decay 1 holds the targets): leave it out\n"
        )
    with pytest.raises(SystemExit):
        ipg_her_recipe.check_args(cli.parse_args(ipg_her_recipe.Args, ["--target-std-floor", "-1"]), [])
    assert "--target-std-floor must be non-negative" in capsys.readouterr().err
