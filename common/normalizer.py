"""Running mean and variance, for normalising observations (and goals) and scaling rewards.

Shared by all three scripts because a saved model is only usable together with the statistics
its inputs were normalised by: the scripts save ``state_dict()`` beside the weights and evaluate
with the statistics frozen. ``InputNormalizer`` is ``ipg_her.py``'s input: observation and goal
normalised separately.

The update merges the statistics of a new batch into the running ones exactly (Chan et al.'s
parallel algorithm), so feeding the data in batches gives the same mean and variance as
``numpy.mean`` / ``numpy.var`` over all of it at once.
"""

import numpy as np
import torch


class RunningMeanStd:
    """Mean and (population) variance of every sample seen by ``update``, feature-wise.

    ``normalize(x) = clip((x - mean) / sqrt(var + eps), -clip, clip)``.
    """

    def __init__(self, shape: tuple[int, ...] = (), eps: float = 1e-8, clip: float = 10.0):
        self.mean = np.zeros(shape, np.float64)
        self.var = np.ones(shape, np.float64)
        self.count = 0.0
        self.eps, self.clip = eps, clip

    def update(self, x: np.ndarray) -> None:
        """Add a batch ``x`` of shape ``(B, *shape)``."""
        x = np.asarray(x, np.float64).reshape(-1, *self.mean.shape)
        n, batch_mean, batch_var = x.shape[0], x.mean(axis=0), x.var(axis=0)
        total = self.count + n
        delta = batch_mean - self.mean
        m2 = self.var * self.count + batch_var * n + delta**2 * self.count * n / total
        self.mean, self.var, self.count = self.mean + delta * n / total, m2 / total, total

    def normalize(self, x: np.ndarray) -> np.ndarray:
        z = (np.asarray(x, np.float64) - self.mean) / np.sqrt(self.var + self.eps)
        return np.clip(z, -self.clip, self.clip).astype(np.float32)

    def __call__(self, x: np.ndarray) -> torch.Tensor:
        """The policy's input: ``normalize(x)`` as a tensor."""
        return torch.as_tensor(self.normalize(x))

    goal_task = False  # as InputNormalizer's, for code that serves both

    def inputs(self, obs: np.ndarray, goal=None) -> torch.Tensor:
        return self(obs)

    def state_dict(self) -> dict:
        return {
            "mean": self.mean.copy(),
            "var": self.var.copy(),
            "count": self.count,
            "clip": self.clip,
        }

    def load_state_dict(self, state: dict) -> None:
        self.mean, self.var = np.asarray(state["mean"]), np.asarray(state["var"])
        self.count, self.clip = float(state["count"]), float(state["clip"])


class InputNormalizer:
    """Policy and critic input: the normalised observation, followed on goal tasks by the
    normalised goal (one statistic for desired and achieved goals)."""

    def __init__(self, obs_dim: int, goal_dim: int):
        self.obs_rms = RunningMeanStd((obs_dim,), clip=5.0)
        self.goal_rms = RunningMeanStd((goal_dim,), clip=5.0)
        self.goal_task = goal_dim > 0

    def update(self, raw) -> None:
        if self.goal_task:
            self.obs_rms.update(raw["observation"])
            self.goal_rms.update(np.concatenate([raw["desired_goal"], raw["achieved_goal"]]))
        else:
            self.obs_rms.update(raw)

    def inputs(self, obs: np.ndarray, goal: np.ndarray | None = None) -> torch.Tensor:
        """The input of observations ``obs`` and, on goal tasks, goals ``goal`` (arrays)."""
        x = self.obs_rms.normalize(obs)
        if self.goal_task:
            x = np.concatenate([x, self.goal_rms.normalize(goal)], axis=-1)
        return torch.as_tensor(x)

    def __call__(self, raw) -> torch.Tensor:
        """The input of a raw environment observation (a Dict on goal tasks)."""
        return self.inputs(raw["observation"], raw["desired_goal"]) if self.goal_task else self.inputs(raw)

    def state_dict(self) -> dict:
        return {"obs_rms": self.obs_rms.state_dict(), "goal_rms": self.goal_rms.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.obs_rms.load_state_dict(state["obs_rms"])
        self.goal_rms.load_state_dict(state["goal_rms"])


class RewardScaler:
    """Rewards divided by the running std of the discounted return (CleanRL's NormalizeReward,
    over a whole rollout at a time). ``returns`` (one per env) carries the discounted return
    from rollout to rollout and restarts where an episode ends."""

    def __init__(self, num_envs: int, gamma: float):
        self.rms, self.returns, self.gamma = RunningMeanStd(()), np.zeros(num_envs), gamma

    def __call__(self, rewards: torch.Tensor, episode_ends: torch.Tensor) -> torch.Tensor:
        """Update the statistics with this rollout's returns, then scale its rewards."""
        returns = np.zeros(rewards.shape)
        for t in range(rewards.shape[0]):
            self.returns[:] = self.returns * self.gamma + rewards[t].numpy()
            returns[t] = self.returns
            self.returns[episode_ends[t].numpy() > 0] = 0.0
        self.rms.update(returns.reshape(-1))
        return rewards / self.std()

    def std(self) -> float:
        return float(np.sqrt(self.rms.var + 1e-8))

    def state_dict(self) -> dict:
        return {"rms": self.rms.state_dict(), "returns": self.returns.copy()}

    def load_state_dict(self, state: dict) -> None:
        self.rms.load_state_dict(state["rms"])
        self.returns[:] = state["returns"]
