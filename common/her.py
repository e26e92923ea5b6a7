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

``HerReplayBuffer`` is ``common/replay.py``'s episode replay plus the goals and the
relabelling. With ``n_sampled_goal = 0`` it stores goals but replays every transition with its
real goal (IPG's ``--no-her`` ablation).
"""

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import gymnasium as gym
import numpy as np

from common.replay import ReplayBuffer

GOAL_SELECTION_STRATEGIES = ("future", "final", "episode")


@dataclass
class HerArgs:
    """HER's flags (goal tasks only), for a script's ``Args`` to inherit."""

    her: bool = True
    """relabel replayed transitions with hindsight goals (goal tasks only)"""
    her_n_sampled_goal: int = 4
    """k: relabelled transitions per real one (relabelled share 1 - 1/(k+1))"""
    her_goal_selection_strategy: Literal["future", "final", "episode"] = "future"
    """where relabelled goals come from: later in the episode, its end, or anywhere in it"""


FLAGS = "--her --her-n-sampled-goal --her-goal-selection-strategy"


def ignored(args: HerArgs, env_id: str, goal_task: bool) -> dict[str, str]:
    """HER's flags a run would ignore, ``{flag: why}``: all without goals, k and the strategy with
    --no-her, the strategy at k = 0."""
    her, k, strategy = FLAGS.split()
    if not goal_task:
        return dict.fromkeys((her, k, strategy), f"{env_id} is not a goal task")
    if not args.her:
        return dict.fromkeys((k, strategy), "--no-her")
    if args.her_n_sampled_goal == 0:
        return {strategy: "--her-n-sampled-goal 0 relabels no goal"}
    return {}


def check(args: HerArgs, env_id: str, goal_task: bool) -> str | None:
    """Why HER's flags cannot serve this run, or None: a negative k, a goal task with ``gamma``
    1 (the script's; its critic's target range is infinite), without a batched reward
    (``reward_refusal``), or one ``hindsight_refusal`` refuses. On a task without goals, says
    that HER is off."""
    if args.her_n_sampled_goal < 0:
        return f"--her-n-sampled-goal must be non-negative, got {args.her_n_sampled_goal}"
    if goal_task and (args.gamma or 0) >= 1:  # sparse_return_range: -1 / (1 - gamma); None: filled in below 1
        return (
            f"--gamma {args.gamma} on a goal task: its returns are bounded by 1 / (1 - gamma), "
            "which needs gamma < 1 (e.g. 0.98)"
        )
    if not goal_task:
        print(f"{env_id} has no goals: hindsight relabelling (HER) is off", flush=True)
    if goal_task and (why := reward_refusal(env_id)):
        return why
    return hindsight_refusal(env_id) if goal_task and args.her else None


def reward_refusal(env_id: str) -> str | None:
    """Why a goal task's ``compute_reward`` cannot serve, or None: relabelling and the critic's
    target range call it on a batch of goals, ``(B, goal_dim)`` each, with ``info=None``."""
    env = gym.make(env_id).unwrapped
    goals = np.zeros((2, *env.observation_space["desired_goal"].shape))
    need = (
        "that takes a batch of goals and returns one reward each; relabelling and the critic's "
        "target range use it (docs/your_goal_task.md)"
    )
    signature = "compute_reward(achieved_goal, desired_goal, info)"
    if not callable(getattr(env, "compute_reward", None)):
        return f"{env_id} has goals but no {signature} {need}"
    try:
        shape = np.shape(env.compute_reward(goals, goals + 1.0, None))
    except Exception as e:  # the task's own code: its message is the user's best clue
        return f"{env_id}'s {signature} raised {type(e).__name__}: {e}; it must be one {need}"
    if shape != (2,):
        return f"{env_id}'s {signature} returned shape {shape} for 2 goals; it must be one {need}"
    return None


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
                f"goal_selection_strategy must be one of {GOAL_SELECTION_STRATEGIES}, got {goal_selection_strategy!r}"
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
        super().add(obs["observation"], actions, rewards, next_obs["observation"], terminations, truncations)
        self.achieved_goal[p] = obs["achieved_goal"]
        self.next_achieved_goal[p] = next_obs["achieved_goal"]
        self.desired_goal[p] = obs["desired_goal"]

    def sample(self, batch_size: int, rng: np.random.Generator | None = None) -> dict:
        """As ``ReplayBuffer.sample``, plus ``achieved_goal, next_achieved_goal, desired_goal``
        (the goal after relabelling) and the boolean ``relabelled``."""
        rng = rng or self.rng
        rows, envs = self._sample_rows(batch_size, rng)
        batch = {
            "obs": self.obs[rows, envs],
            "actions": self.actions[rows, envs],
            "rewards": self.rewards[rows, envs].copy(),
            "next_obs": self.next_obs[rows, envs],
            "terminations": self.terminations[rows, envs],
            "achieved_goal": self.achieved_goal[rows, envs],
            "next_achieved_goal": self.next_achieved_goal[rows, envs],
            "desired_goal": self.desired_goal[rows, envs].copy(),
        }
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
            batch["rewards"][relabel] = self.compute_reward(batch["next_achieved_goal"][relabel], new_goal)
        return batch


def hindsight_refusal(env_id: str) -> str | None:
    """Why HER cannot serve this goal task, or None. HER keeps a transition's stored
    ``terminated``: where termination depends on the goal (``compute_terminated``, e.g. PointMaze
    with continuing_task=False), relabelled transitions would carry wrong flags."""
    env = gym.make(env_id).unwrapped  # gymnasium 1.x wrappers do not forward attributes
    goal = np.zeros(env.observation_space["desired_goal"].shape)
    if hasattr(env, "compute_terminated"):
        if any(np.any(env.compute_terminated(g, goal, {})) for g in (goal, goal + 1e3)):
            return (
                f"{env_id} terminates depending on the goal; HER would keep the stored "
                "termination of a relabelled transition: use --no-her"
            )
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
