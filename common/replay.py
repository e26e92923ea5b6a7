"""Episode replay: the transitions of finished episodes, sampled uniformly (Q-Prop's critic,
and IPG's on tasks without goals; ``common/her.py`` adds the goals and their relabelling).

Storage is circular, ``(rows, num_envs, ...)``: one row per vector-env step, so the N envs of a
gymnasium vector environment write side by side and every episode lies in one column. When the
write position wraps round onto a stored episode, that whole episode stops being sampled, so
``future`` goals never come from overwritten steps.
"""

import gymnasium as gym
import numpy as np
import torch

from common.tasks import available_memory, goal_space, task_name


class ReplayBuffer:
    """Episode replay: transitions of finished episodes, sampled uniformly.

    Args:
        buffer_size: transitions kept, over all envs.
        num_envs: parallel environments writing one transition each per ``add``.
        obs_dim, act_dim: sizes.
        seed: of the sampling generator.
    """

    def __init__(self, buffer_size: int, num_envs: int, obs_dim: int, act_dim: int, seed=None):
        self.rows, self.num_envs = buffer_size // num_envs, num_envs
        self.rng = np.random.default_rng(seed)
        shape = (self.rows, num_envs)
        self.obs = np.zeros((*shape, obs_dim), np.float32)
        self.next_obs = np.zeros((*shape, obs_dim), np.float32)
        self.actions = np.zeros((*shape, act_dim), np.float32)
        self.rewards = np.zeros(shape, np.float32)
        self.terminations = np.zeros(shape, np.float32)
        self.ep_start = np.zeros(shape, np.int64)  # row where the transition's episode starts
        self.ep_length = np.zeros(shape, np.int64)  # its length once finished, 0 before
        self.current_start = np.zeros(num_envs, np.int64)  # where each unfinished episode starts
        self.current_length = np.zeros(num_envs, np.int64)
        self.pos, self.filled = 0, 0  # next row to write, rows written so far (at most rows)
        self._sampleable = None  # flat indices of sampleable transitions, cached between adds

    def add(self, obs, actions, rewards, next_obs, terminations, truncations) -> None:
        """Store one vector-env step: every argument has leading dimension ``num_envs``.

        ``next_obs`` is the real next observation (the final one where the episode ended, not
        the reset observation a vector env returns in its place).
        """
        p = self.pos
        for e in np.flatnonzero(self.ep_length[p] > 0):  # overwriting a stored episode: drop it
            self.ep_length[(self.ep_start[p, e] + np.arange(self.ep_length[p, e])) % self.rows, e] = 0
        if np.any(self.current_length >= self.rows):
            raise ValueError(f"an episode is longer than the buffer's {self.rows} rows per env; enlarge buffer_size")
        self.obs[p], self.next_obs[p], self.actions[p] = obs, next_obs, actions
        self.rewards[p], self.terminations[p] = rewards, terminations
        self.ep_start[p], self.ep_length[p] = self.current_start, 0
        self.current_length += 1
        self.pos, self.filled = (p + 1) % self.rows, min(self.filled + 1, self.rows)
        self._finish_episodes(np.logical_or(terminations, truncations))

    def _finish_episodes(self, ended: np.ndarray) -> None:
        """Open the current episodes of the envs where ``ended`` to sampling; the next ones start
        at the write position."""
        for e in np.flatnonzero(ended):
            length = self.current_length[e]
            self.ep_length[(self.current_start[e] + np.arange(length)) % self.rows, e] = length
            self.current_start[e], self.current_length[e] = self.pos, 0
        self._sampleable = None

    def end_episodes(self) -> None:
        """Open the unfinished episodes to sampling as if truncated now (a resume point of
        earlier code, without the environments' state, restarts them, so they never go on);
        their last next_obs stays the bootstrap state."""
        self._finish_episodes(self.current_length > 0)

    def state_dict(self) -> dict:
        """The stored rows, the write position and the sampler's state (for resuming a run)."""
        arrays = {
            k: v[: self.filled]
            for k, v in vars(self).items()  # the (rows, envs) arrays
            if isinstance(v, np.ndarray) and v.shape[:2] == (self.rows, self.num_envs)
        }
        return arrays | {
            "current_start": self.current_start.copy(),
            "current_length": self.current_length.copy(),
            "pos": self.pos,
            "filled": self.filled,
            "rng": self.rng.bit_generator.state,
        }

    def load_state_dict(self, state: dict) -> None:
        for key, value in state.items():
            if key.startswith("_"):  # a cache that files of earlier code could hold: rebuilt
                continue
            if key == "rng":
                self.rng.bit_generator.state = value
            elif isinstance(value, np.ndarray) and getattr(self, key).shape[1:] == value.shape[1:]:
                getattr(self, key)[: len(value)] = value
            elif isinstance(value, np.ndarray):
                raise ValueError(f"replay state {key!r} has shape {value.shape}, this buffer {getattr(self, key).shape}")
            else:
                setattr(self, key, value)
        self._sampleable = None

    def sampleable(self) -> np.ndarray:
        """Flat indices (row * num_envs + env) of the transitions of finished, kept episodes."""
        if self._sampleable is None:
            self._sampleable = np.flatnonzero(self.ep_length[: self.filled])
        return self._sampleable

    def num_sampleable(self) -> int:
        return len(self.sampleable())

    def _sample_rows(self, batch_size: int, rng: np.random.Generator):
        flat = self.sampleable()
        if len(flat) == 0:
            raise ValueError("no finished episode stored yet")
        return np.divmod(rng.choice(flat, batch_size), self.num_envs)

    def sample(self, batch_size: int, rng: np.random.Generator | None = None) -> dict:
        """Transitions of finished episodes, uniformly: ``obs, actions, rewards, next_obs,
        terminations`` (the names of the stored arrays). ``rng``: draw from this generator
        instead of the buffer's own (a measurement that must not move the training's stream)."""
        rows, envs = self._sample_rows(batch_size, rng or self.rng)
        return {
            "obs": self.obs[rows, envs],
            "actions": self.actions[rows, envs],
            "rewards": self.rewards[rows, envs].copy(),
            "next_obs": self.next_obs[rows, envs],
            "terminations": self.terminations[rows, envs],
        }


def sample_replay(rb: ReplayBuffer, norm, reward_scale: float, batch_size: int, count: int = 1, rng=None) -> list[dict]:
    """``count`` replay batches of tensors, inputs normalised, rewards scaled: one draw of
    ``count * batch_size`` transitions, split (``rng``: a generator other than the buffer's)."""
    data = rb.sample(batch_size * count, rng)
    goal = data["desired_goal"] if norm.goal_task else None  # after HER's relabelling
    tensors = {
        "obs": norm.inputs(data["obs"], goal),
        "next_obs": norm.inputs(data["next_obs"], goal),
        "actions": torch.as_tensor(data["actions"]),
        "rewards": torch.as_tensor(data["rewards"] * reward_scale),
        "terminations": torch.as_tensor(data["terminations"]),
    }
    chunks = {key: t.split(batch_size) for key, t in tensors.items()}
    return [{key: chunks[key][i] for key in chunks} for i in range(count)]


def buffer_refusal(buffer_size: int, num_envs: int, env_id: str) -> str | None:
    """Why a buffer of ``buffer_size`` transitions cannot serve ``env_id``, or None: replay
    samples finished episodes only, so each env's rows must hold its longest episode; and its
    arrays (``HerReplayBuffer``'s on a goal task) must fit in the available memory."""
    rows, longest = buffer_size // num_envs, gym.spec(task_name(env_id)).max_episode_steps
    if longest and rows < longest:
        return (
            f"--buffer-size {buffer_size} keeps {rows} steps per env, less than one "
            f"{env_id} episode ({longest} steps); enlarge it"
        )
    env = gym.make(env_id)
    space, act_dim = env.observation_space, gym.spaces.flatdim(env.action_space)
    env.close()
    obs_dim, goal_dim = gym.spaces.flatdim(space), 0
    if goal_space(space):  # observation and goals apart (common/her.py)
        obs_dim, goal_dim = space["observation"].shape[0], space["desired_goal"].shape[0]
    # float32 obs, next_obs, actions, reward, termination, goals; int64 episode start and length
    need = rows * num_envs * (4 * (2 * obs_dim + act_dim + 2 + 3 * goal_dim) + 16)
    if need > (free := available_memory()):
        return (
            f"--buffer-size {buffer_size} needs about {need / 2**30:,.1f} GiB of memory, and "
            f"{free / 2**30:.1f} GiB are available; make it smaller"
        )
    return None
