"""A user's own task that is valid gymnasium but odd (tests/odd_tasks.py): it trains, or it is
one ``error:`` line before any run folder exists; its saved policy evaluates only where it fits."""

import pytest
import torch
from conftest import assert_clean_error, parse, run_dirs, run_script

import ipg_her_recipe
from common import checkpoint, evaluate

TINY = ("--total-timesteps", "200", "--eval-freq", "0", "--eval-episodes", "2")


def test_infinite_action_bounds_are_no_nan_and_the_model_is_saved(tmp_path):
    """A Box without bounds gives the critic infinite bounds to clamp to: the model guard
    (no NaN or infinity replaces a good model) must not take them for a diverged weight."""
    flags = ("--env-id", "tests.odd_tasks:UnboundedPointGoal-v0", *TINY, "--save-model")
    result = run_script("ipg_her.py", tmp_path, *flags, "--save-freq", "100")
    assert result.returncode == 0, result.stderr
    (run_dir,) = run_dirs(tmp_path)
    content = torch.load(run_dir / "model.pt", weights_only=True)
    assert torch.isinf(content["qf"]["low"]).all()  # the bounds as the task gave them
    policy = evaluate.load_policy(str(run_dir), "tests.odd_tasks:UnboundedPointGoal-v0")
    assert len(policy.evaluate([1])[0]) == 1


def test_a_nan_in_the_bounds_is_still_refused():
    bounds = {"qf": {"low": torch.tensor([float("nan")]), "high": torch.tensor([float("inf")])}}
    assert checkpoint.not_finite(bounds) == ["qf.low"]
    assert checkpoint.not_finite({"qf": {"weight": torch.tensor([float("inf")])}}) == ["qf.weight"]


@pytest.mark.parametrize(
    "env_id, needles",
    [
        ("RaisingRewardGoal-v0", ("compute_reward", "ValueError: info must be a dict")),
        ("GridObs-v0", ("observations have shape (2, 2)", "vectors")),
        ("GridActions-v0", ("actions have shape (2, 1)", "vectors")),
    ],
)
def test_a_task_the_scripts_cannot_drive_is_one_line_before_any_run_folder(tmp_path, env_id, needles):
    result = run_script("ipg_her.py", tmp_path / "runs", "--env-id", f"tests.odd_tasks:{env_id}")
    assert_clean_error(result, *needles)
    assert not (tmp_path / "runs").exists()


def test_a_one_step_horizon_keeps_the_default_discount():
    """gamma = 1 - 1/H is 0 at H = 1, which --gamma refuses: the recipe fills in 0.98 there, as without a horizon."""
    args = parse(ipg_her_recipe, "--env-id", "tests.odd_tasks:OneStepPointGoal-v0")
    assert args.gamma == 0.98


def trained(log_dir, env_id: str):
    result = run_script("ipg_her.py", log_dir, "--env-id", env_id, *TINY, "--save-model")
    assert result.returncode == 0, result.stderr
    return run_dirs(log_dir)[0] / "model.pt"


@pytest.fixture(scope="module")
def goal_model(tmp_path_factory):
    return trained(tmp_path_factory.mktemp("goal"), "tests.point_goal:PointGoal-v0")


def test_a_policy_on_a_task_of_its_input_size_but_not_its_kind_is_refused(goal_model, tmp_path):
    """PointGoal's policy reads observation and desired goal (2 + 2), Vector4's a vector of 4:
    the sizes agree, the observations do not, either way round."""
    with pytest.raises(ValueError, match="takes a goal Dict as its observation"):
        evaluate.load_policy(str(goal_model), "tests.odd_tasks:Vector4-v0")
    vector_model = trained(tmp_path, "tests.odd_tasks:Vector4-v0")
    with pytest.raises(ValueError, match="takes a vector as its observation"):
        evaluate.load_policy(str(vector_model), "tests.point_goal:PointGoal-v0")


@pytest.mark.parametrize("field", ["args", "last_eval_seeds", "normalizer_class"])
def test_a_model_file_missing_a_field_is_one_line(goal_model, tmp_path, field):
    content = torch.load(goal_model, weights_only=True)
    del content[field]
    torch.save(content, tmp_path / "model.pt")
    with pytest.raises(checkpoint.CheckpointError, match=f"lacks a readable {field}"):
        evaluate.load_policy(str(tmp_path / "model.pt"), "tests.point_goal:PointGoal-v0")
