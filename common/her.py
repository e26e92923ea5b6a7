"""Episode replay with Hindsight Experience Replay (paper Figure 2; Andrychowicz et al. 2017).

HER turns failures into lessons. An episode that missed its goal ``g`` still shows how to reach
the places it *did* reach: replaying a transition ``(s_t || g', a_t, r', s_{t+1} || g')`` with a
goal ``g'`` achieved later in the same episode gives a transition whose reward is informative
even when the real reward was -1 at every step. Figure 2 of the paper stores the relabelled
copies; like Stable-Baselines3 we relabel *at sample time* instead, which stores each transition
once and lets the relabelled share be exact:

* a share ``1 - 1 / (n_sampled_goal + 1)`` of every sampled batch is relabelled (k = 4: 0.8);
* ``goal_selection_strategy`` picks the new goal g' for the transition at step t of an episode
  of T steps. Write ``ag_{j+1}`` for the achieved goal of the state reached by transition j:

  - ``future``:  g' = ag_{j+1}, j uniform in [t, T-1]: a state *after* s_t, possibly s_{t+1}
    itself (as Stable-Baselines3 and OpenAI baselines both do: g' may be reached at once);
  - ``final``:   g' = ag_T, the episode's last achieved goal;
  - ``episode``: g' = ag_{j+1}, j uniform in [0, T-1];

* the reward of a relabelled transition is recomputed from the **next** achieved goal,
  ``r' = compute_reward(ag_{t+1}, g')`` (using ag_t is the classic off-by-one);
* only finished episodes are sampled (``future`` needs the episode's end);
* ``terminated`` is stored as the environment reported it. FetchReach never terminates: its
  time-limit ends are truncations, which keep bootstrapping (the critic's target uses s_{t+1}).

``ReplayBuffer`` is the plain episode replay underneath (Q-Prop's, and IPG's on tasks without
goals); ``HerReplayBuffer`` adds the goals and the relabelling. With ``n_sampled_goal = 0`` it
stores goals but replays every transition with its real goal (IPG's ``--no-her`` ablation).

Storage is circular, ``(rows, num_envs, ...)``: one row per vector-env step, so the N envs of a
gymnasium vector environment write side by side and every episode lies in one column. When the
write position wraps round onto a stored episode, that whole episode stops being sampled, so
``future`` goals never come from overwritten steps.
"""

from collections.abc import Callable

import gymnasium as gym
import numpy as np
import torch

GOAL_SELECTION_STRATEGIES = ("future", "final", "episode")


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
            self.ep_length[
                (self.ep_start[p, e] + np.arange(self.ep_length[p, e])) % self.rows, e
            ] = 0
        if np.any(self.current_length >= self.rows):
            raise ValueError(
                f"an episode is longer than the buffer's {self.rows} rows per env; "
                "enlarge buffer_size"
            )
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
        """Open the unfinished episodes to sampling as if truncated now (a resumed run restarts
        its environments, so they never go on); their last next_obs stays the bootstrap state."""
        self._finish_episodes(self.current_length > 0)

    def state_dict(self) -> dict:
        """The stored rows, the write position and the sampler's state (for resuming a run)."""
        arrays = {
            k: v[: self.filled]
            for k, v in vars(self).items()  # the (rows, envs) arrays
            if isinstance(v, np.ndarray) and v.shape[:2] == (self.rows, self.num_envs)
        }
        return arrays | {"current_start": self.current_start.copy(),
                         "current_length": self.current_length.copy(), "pos": self.pos,
                         "filled": self.filled, "rng": self.rng.bit_generator.state}  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        for key, value in state.items():
            if key.startswith("_"):  # a cache that files of earlier code could hold: rebuilt
                continue
            if key == "rng":
                self.rng.bit_generator.state = value
            elif isinstance(value, np.ndarray) and getattr(self, key).shape[1:] == value.shape[1:]:
                getattr(self, key)[: len(value)] = value
            elif isinstance(value, np.ndarray):
                raise ValueError(f"replay state {key!r} has shape {value.shape}, this buffer "
                                 f"{getattr(self, key).shape}")  # fmt: skip
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
            "obs": self.obs[rows, envs], "actions": self.actions[rows, envs],
            "rewards": self.rewards[rows, envs].copy(), "next_obs": self.next_obs[rows, envs],
            "terminations": self.terminations[rows, envs],
        }  # fmt: skip


class HerReplayBuffer(ReplayBuffer):
    """Episode replay of a goal task, a share ``1 - 1/(n_sampled_goal + 1)`` of every batch
    relabelled with hindsight goals.

    Args (besides ``ReplayBuffer``'s):
        goal_dim: size of a goal.
        compute_reward: ``(achieved_goal, desired_goal) -> reward``, vectorised over a batch
            ``(B, goal_dim)``; for gymnasium-robotics tasks
            ``lambda ag, g: env.unwrapped.compute_reward(ag, g, None)``.
        n_sampled_goal: k, relabelled transitions per real one (0: no relabelling).
        goal_selection_strategy: ``future``, ``final`` or ``episode``.
    """

    def __init__(
        self,
        buffer_size: int,
        num_envs: int,
        obs_dim: int,
        act_dim: int,
        goal_dim: int,
        compute_reward: Callable[[np.ndarray, np.ndarray], np.ndarray],
        n_sampled_goal: int = 4,
        goal_selection_strategy: str = "future",
        seed=None,
    ):
        if goal_selection_strategy not in GOAL_SELECTION_STRATEGIES:
            raise ValueError(
                f"goal_selection_strategy must be one of {GOAL_SELECTION_STRATEGIES}, "
                f"got {goal_selection_strategy!r}"
            )
        if n_sampled_goal < 0:
            raise ValueError(f"n_sampled_goal must be >= 0, got {n_sampled_goal}")
        super().__init__(buffer_size, num_envs, obs_dim, act_dim, seed)
        self.compute_reward, self.strategy = compute_reward, goal_selection_strategy
        self.her_ratio = 1.0 - 1.0 / (n_sampled_goal + 1)
        shape = (self.rows, num_envs, goal_dim)
        self.achieved_goal = np.zeros(shape, np.float32)  # ag_t
        self.next_achieved_goal = np.zeros(shape, np.float32)  # ag_{t+1}
        self.desired_goal = np.zeros(shape, np.float32)

    def add(self, obs: dict, actions, rewards, next_obs: dict, terminations, truncations) -> None:
        """As ``ReplayBuffer.add``, with ``obs`` and ``next_obs`` a goal task's Dicts
        (``observation``, ``achieved_goal``, ``desired_goal``): ``next_obs`` is the real next."""
        p = self.pos
        super().add(obs["observation"], actions, rewards, next_obs["observation"], terminations,
                    truncations)  # fmt: skip
        self.achieved_goal[p] = obs["achieved_goal"]
        self.next_achieved_goal[p] = next_obs["achieved_goal"]
        self.desired_goal[p] = obs["desired_goal"]

    def sample(self, batch_size: int, rng: np.random.Generator | None = None) -> dict:
        """As ``ReplayBuffer.sample``, plus ``achieved_goal, next_achieved_goal, desired_goal``
        (the goal after relabelling) and the boolean ``relabelled``."""
        rng = rng or self.rng
        rows, envs = self._sample_rows(batch_size, rng)
        batch = {
            "obs": self.obs[rows, envs], "actions": self.actions[rows, envs],
            "rewards": self.rewards[rows, envs].copy(), "next_obs": self.next_obs[rows, envs],
            "terminations": self.terminations[rows, envs],
            "achieved_goal": self.achieved_goal[rows, envs],
            "next_achieved_goal": self.next_achieved_goal[rows, envs],
            "desired_goal": self.desired_goal[rows, envs].copy(),
        }  # fmt: skip
        # HER (the paper's Figure 2): a share her_ratio of the transitions get a goal achieved
        relabel = rng.random(batch_size) < self.her_ratio  # later, and the reward it implies
        batch["relabelled"] = relabel
        if relabel.any():
            r, e = rows[relabel], envs[relabel]
            start, length = self.ep_start[r, e], self.ep_length[r, e]
            t = (r - start) % self.rows  # step of the transition within its episode
            if self.strategy == "future":
                j = rng.integers(t, length)  # uniform in [t, T-1]
            elif self.strategy == "final":
                j = length - 1
            else:  # episode
                j = rng.integers(0, length)
            new_goal = self.next_achieved_goal[(start + j) % self.rows, e]  # g' = ag_{j+1}
            batch["desired_goal"][relabel] = new_goal
            # r' from ag_{t+1}, the achieved goal of the state the transition reached
            batch["rewards"][relabel] = self.compute_reward(
                batch["next_achieved_goal"][relabel], new_goal
            )
        return batch


def hindsight_refusal(env_id: str) -> str | None:
    """Why HER cannot serve this goal task, or None. HER keeps a transition's stored
    ``terminated``: where termination depends on the goal (``compute_terminated``, e.g. PointMaze
    with continuing_task=False), relabelled transitions would carry wrong flags."""
    env = gym.make(env_id).unwrapped  # gymnasium 1.x wrappers do not forward attributes
    goal = np.zeros(env.observation_space["desired_goal"].shape)
    if hasattr(env, "compute_terminated"):
        if any(np.any(env.compute_terminated(g, goal, {})) for g in (goal, goal + 1e3)):
            return (f"{env_id} terminates depending on the goal; HER would keep the stored "
                    "termination of a relabelled transition: use --no-her")  # fmt: skip
    return None


def goal_task_reward(env_id: str, her: bool = True) -> Callable:
    """A goal task's reward ``(achieved_goal, desired_goal) -> r``, vectorised, for relabelling;
    a task ``hindsight_refusal`` refuses raises ``ValueError`` (unless ``her`` is off)."""
    if her and (why := hindsight_refusal(env_id)):
        raise ValueError(why)
    env = gym.make(env_id).unwrapped
    return lambda achieved_goal, desired_goal: env.compute_reward(achieved_goal, desired_goal, None)


def sparse_return_range(compute_reward, goal_dim: int, gamma: float) -> tuple | None:
    """[-1/(1-gamma), 0], the returns Fetch's reward allows (0 where the goal is reached, -1
    elsewhere), if ``compute_reward`` is that reward; None for any other (PointMaze's is 0/+1)."""
    goal = np.zeros((2, goal_dim))
    far = goal + np.array([[0.0], [1e3]])
    rewards = np.asarray(compute_reward(far, goal), np.float64)
    return (-1.0 / (1.0 - gamma), 0.0) if rewards.tolist() == [0.0, -1.0] else None


def sample_replay(rb: ReplayBuffer, norm, reward_scale: float, batch_size: int,
                  count: int = 1, rng=None) -> list[dict]:  # fmt: skip
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
