"""Valid gymnasium tasks of a user's, each odd in one way the scripts must meet with a run or
one ``error:`` line (tests/test_user_tasks.py). Imported by ``--env-id tests.odd_tasks:ID``."""

import gymnasium as gym
import numpy as np

from tests.point_goal import PointGoal


class UnboundedPointGoal(PointGoal):
    """PointGoal whose actions are a Box without bounds (valid gymnasium: Box(-inf, inf))."""

    def __init__(self):
        super().__init__()
        self.action_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)


class RaisingRewardGoal(PointGoal):
    """A goal task whose compute_reward fails with the user's own message."""

    def compute_reward(self, achieved_goal, desired_goal, info):
        raise ValueError("info must be a dict of this task's own")


class Grid(gym.Env):
    """A Box task whose observations (``obs_shape``) or actions (``act_shape``) are not vectors."""

    def __init__(self, obs_shape=(4,), act_shape=(2,)):
        self.observation_space = gym.spaces.Box(-1.0, 1.0, obs_shape, np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, act_shape, np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(self.observation_space.shape), {}

    def step(self, action):
        return np.zeros(self.observation_space.shape), 0.0, False, False, {}


register = dict(max_episode_steps=10)
gym.register("UnboundedPointGoal-v0", entry_point=UnboundedPointGoal, **register)
gym.register("RaisingRewardGoal-v0", entry_point=RaisingRewardGoal, **register)
gym.register("GridObs-v0", entry_point=Grid, kwargs=dict(obs_shape=(2, 2)), **register)
gym.register("GridActions-v0", entry_point=Grid, kwargs=dict(act_shape=(2, 1)), **register)
gym.register("Vector4-v0", entry_point=Grid, **register)  # PointGoal's policy input size, a Box
gym.register("OneStepPointGoal-v0", entry_point=PointGoal, max_episode_steps=1)
