"""Tiny hand-written environments whose every observation says where it came from."""

import gymnasium as gym
import numpy as np


class CountingEnv(gym.Env):
    """obs = [episode number, step within the episode]; truncates after ``limit`` steps and
    terminates early, at random, when the first action component is large."""

    def __init__(self, limit: int = 5):
        self.limit, self.episode, self.t = limit, -1, 0
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def _obs(self):
        return np.array([self.episode % 8, self.t], np.float64)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.episode, self.t = self.episode + 1, 0
        return self._obs(), {}

    def step(self, action):
        self.t += 1
        terminated = bool(action[0] > 0.9 and self.t >= 2)
        truncated = self.t >= self.limit and not terminated
        return self._obs(), 1.0, terminated, truncated, {}


class CountingGoalEnv(CountingEnv):
    """CountingEnv as a goal task: observation = achieved goal = [episode, step], desired goal =
    [episode, -1]."""

    def __init__(self, limit: int = 5):
        super().__init__(limit)
        box = gym.spaces.Box(-np.inf, np.inf, (2,), np.float64)
        self.observation_space = gym.spaces.Dict({"observation": box, "achieved_goal": box, "desired_goal": box})

    def _obs(self):
        now = super()._obs()
        return {
            "observation": now,
            "achieved_goal": now.copy(),
            "desired_goal": np.array([self.episode % 8, -1.0]),
        }


def counting_envs(num_envs: int, goal: bool = False) -> gym.vector.SyncVectorEnv:
    """``num_envs`` CountingEnvs (CountingGoalEnvs with ``goal``) in a SAME_STEP vector env, as
    the scripts run theirs."""
    env_class = CountingGoalEnv if goal else CountingEnv
    return gym.vector.SyncVectorEnv(
        [lambda: gym.wrappers.RecordEpisodeStatistics(env_class(limit=5)) for _ in range(num_envs)],
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
    )
