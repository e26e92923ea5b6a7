"""A goal task of your own: a point in the plane sent to a goal (docs/your_goal_task.md).

python ipg_her_recipe.py --env-id tests.point_goal:PointGoal-v0
"""

import gymnasium as gym
import numpy as np


class PointGoal(gym.Env):
    """The point moves by 0.1 * action per step; 0 reward within 0.1 of the goal, -1 elsewhere."""

    def __init__(self, distance_threshold: float = 0.1):
        self.distance_threshold = distance_threshold
        box = gym.spaces.Box(-1.0, 1.0, (2,), np.float64)
        self.observation_space = gym.spaces.Dict(  # what HER needs: the goals apart
            {"observation": box, "achieved_goal": box, "desired_goal": box}
        )
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def compute_reward(self, achieved_goal, desired_goal, info):  # vectorised: HER relabels
        distance = np.linalg.norm(achieved_goal - desired_goal, axis=-1)
        return -(distance > self.distance_threshold).astype(np.float32)

    def _obs(self):
        return {"observation": self.point.copy(), "achieved_goal": self.point.copy(), "desired_goal": self.goal.copy()}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.point, self.goal = self.np_random.uniform(-1.0, 1.0, (2, 2))
        return self._obs(), {}

    def step(self, action):
        self.point = np.clip(self.point + 0.1 * np.clip(action, -1.0, 1.0), -1.0, 1.0)
        reward = float(self.compute_reward(self.point, self.goal, None))
        # never terminated: the episode's end must not depend on the goal, which HER rewrites
        return self._obs(), reward, False, False, {"is_success": reward == 0.0}


gym.register("PointGoal-v0", entry_point=PointGoal, max_episode_steps=50)
