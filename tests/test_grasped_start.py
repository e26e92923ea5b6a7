"""common/grasped_start.py: the HER paper's pick-and-place starts (sec. 4.1), on the real task."""

import runpy
import sys

import gymnasium as gym
import numpy as np
import pytest
from conftest import ROOT, assert_clean_error, run_script

from common import evaluate, tasks
from common.grasped_start import GraspedStart, refusal

tasks.register_goal_tasks()
TASK = "FetchPickAndPlace-v4"


def starts(share: float, n: int, seed: int = 0) -> list[tuple[dict, bool]]:
    """``n`` resets of a wrapped env; each (obs, whether the object lifts when the arm rises
    for 8 steps with the gripper shut)."""
    env, out = GraspedStart(gym.make(TASK), share), []
    for i in range(n):
        obs, _ = env.reset(seed=seed if i == 0 else None)
        last = obs
        for _ in range(8):
            last = env.step(np.array([0.0, 0.0, 1.0, -1.0]))[0]
        out.append((obs, last["observation"][5] - obs["observation"][5] > 0.05))
    env.close()
    return out


def test_a_grasped_start_holds_the_object_between_the_fingers_and_lifts_it():
    for obs, lifted in starts(1.0, 4):
        gap = np.linalg.norm(obs["observation"][6:9])  # object minus gripper position
        assert gap < 0.02 and lifted  # in the gripper, and it stays there when the arm rises
    for obs, lifted in starts(0.0, 4):  # the task's own starts: object apart on the table
        assert np.linalg.norm(obs["observation"][6:9]) > 0.05 and not lifted


def test_the_share_of_grasped_starts_is_share_and_the_seed_repeats_them():
    held = [lifted for _, lifted in starts(0.5, 60)]
    assert 0.3 < np.mean(held) < 0.7  # 60 draws of p = 0.5: 0.3-0.7 fails once in ~10^3
    assert [lifted for _, lifted in starts(0.5, 60)] == held  # the same seed, the same starts


def test_tasks_without_a_free_gripper_are_refused():
    assert refusal(TASK) is None
    assert "FetchPush-v4" in refusal("FetchPush-v4") and refusal("FetchSlide-v4")


@pytest.mark.parametrize(
    ("flags", "needle"),
    [
        (("--env-id", "FetchPush-v4", "--grasped-start", "0.5"), "gripper can hold"),
        (("--env-id", TASK, "--grasped-start", "1.5"), "in [0, 1]"),
    ],
)
def test_the_recipe_refuses_grasped_starts_it_cannot_make(tmp_path, flags, needle):
    assert_clean_error(run_script("ipg_her_recipe.py", tmp_path, *flags), needle)


def test_pick_and_place_trains_from_grasped_starts_and_evaluates_from_the_tasks_own(monkeypatch, tmp_path):
    """ipg_her_recipe.py --grasped-start 1: every training episode starts with the object
    between the fingers (the flag reaches the training envs); every evaluation episode starts as
    the task does, the object apart on the table (the published success rates are the task's)."""
    train_gaps, eval_gaps, calls = [], [], [0]
    reset = GraspedStart.reset

    def recording_reset(self, **kwargs):
        obs, info = reset(self, **kwargs)
        train_gaps.append(np.linalg.norm(obs["observation"][6:9]))  # object minus gripper
        return obs, info

    policy_call = evaluate.Policy.__call__

    def recording_call(self, obs, stochastic=False):
        if calls[0] % 50 == 0:  # an episode's first step (50 steps each)
            eval_gaps.append(np.linalg.norm(obs["observation"][6:9]))
        calls[0] += 1
        return policy_call(self, obs, stochastic)

    argv = [
        "ipg_her_recipe.py",
        "--env-id",
        "FetchPickAndPlace-v4",
        "--grasped-start",
        "1.0",
        "--total-timesteps",
        "200",
        "--critic-steps",
        "2",
        "--eval-freq",
        "100",
        "--eval-episodes",
        "3",
        "--eval-workers",
        "0",
        "--log-dir",
        str(tmp_path),
    ]
    monkeypatch.setattr(GraspedStart, "reset", recording_reset)
    monkeypatch.setattr(evaluate.Policy, "__call__", recording_call)
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit) as done:
        runpy.run_path(str(ROOT / "ipg_her_recipe.py"), run_name="__main__")
    assert done.value.code == 0
    assert len(train_gaps) >= 2 and max(train_gaps) < 0.02  # both envs' starts, grasped
    assert len(eval_gaps) == 6 and min(eval_gaps) > 0.05  # two evaluations of 3, on the table
