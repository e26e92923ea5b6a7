"""common/grasped_start.py: the HER paper's pick-and-place starts (sec. 4.1), on the real task."""

import gymnasium as gym
import numpy as np
import pytest
from conftest import assert_clean_error, run_script

from common import tasks
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
    [(("--env-id", "FetchPush-v4", "--grasped-start", "0.5"), "gripper can hold"),
     (("--env-id", TASK, "--grasped-start", "1.5"), "in [0, 1]")],
)  # fmt: skip
def test_the_recipe_refuses_grasped_starts_it_cannot_make(tmp_path, flags, needle):
    assert_clean_error(run_script("ipg_her_recipe.py", tmp_path, *flags), needle)
