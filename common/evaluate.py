"""Load, evaluate and watch a saved policy of any of the three scripts.

    python -m common.evaluate runs/FetchReach-v4__ipg_her__1__1795420633      # its model.pt
    python -m common.evaluate runs/.../model.pt --episodes 50 --seed 7 --capture-video

From Python (a notebook), on raw environment observations (a Dict on goal tasks):

    policy = load_policy("runs/.../model.pt")
    action = policy(obs)

The policy is rebuilt from the checkpoint alone: its ``script`` and ``args`` say which networks,
task and sizes, and the normaliser's statistics are frozen as they were saved. Without
``--seed``, the episodes are the ones the run's last evaluation played before the save, so for
the model.pt a finished run saves at its end, right after that evaluation, the mean return
printed here is the run's own last ``eval/episodic_return``. A checkpoint saved mid-way
(``--save-freq``, or at an interruption) holds weights newer than the evaluated ones: the same
episodes, not the same numbers.
"""

import collections
import copy
import importlib
import multiprocessing
import os
import signal
import sys
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch
import tyro

from common import checkpoint, cli, seeding
from common.normalizer import InputNormalizer, RunningMeanStd

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@dataclass
class Args:
    path: tyro.conf.Positional[str]
    """a model.pt written with --save-model, or the run folder holding it"""
    episodes: int | None = None
    """episodes to run (default: as many as the run's last evaluation)"""
    seed: int | None = None
    """seed of fresh evaluation episodes (default: replay the run's last evaluation's episodes)"""
    stochastic: bool = False
    """sample actions from the Gaussian policy instead of taking its mean"""
    capture_video: bool = False
    """record the episodes into the run folder's videos/evaluate (needs moviepy and a renderer)"""
    env_id: str | None = None
    """evaluate on another task with the same observation and action spaces"""


class Policy:
    """A saved policy as a function of a raw environment observation: ``action = policy(obs)``."""

    def __init__(self, script, agent, normalizer, env_id: str, state: dict, raw_spaces: tuple):
        self.script, self.agent, self.normalizer = script, agent, normalizer
        self.env_id, self.args = env_id, state["args"]
        self.last_eval_seeds = state["last_eval_seeds"]
        self.obs_space, action_space = raw_spaces  # the environment's own, before any wrapper
        self.low, self.high = action_space.low, action_space.high

    def __call__(self, obs, stochastic: bool = False) -> np.ndarray:
        if self.script.__name__ == "ipg_her":
            x = self.normalizer.raw(obs)[None]
        else:  # PPO-KL and Q-Prop flatten a goal Dict into one vector, as their make_env does
            flat = gym.spaces.flatten(self.obs_space, obs) if isinstance(obs, dict) else obs
            x = torch.as_tensor(self.normalizer.normalize(flat)[None])
        with torch.no_grad():
            action = self.agent.dist(x).sample() if stochastic else self.agent.actor_mean(x)
        return np.clip(action.numpy()[0], self.low, self.high)

    def evaluate(self, seeds: list[int], stochastic=False, video_dir=None):
        """The script's own ``evaluate``: episodic returns and, on goal tasks, successes."""
        norm = self.normalizer
        return self.script.evaluate(self.agent, norm, self.env_id, seeds, video_dir, stochastic)


def load_policy(path: str, env_id: str | None = None) -> Policy:
    """The policy saved at ``path`` (a model.pt or its run folder), optionally on another task
    whose spaces match. Raises ``checkpoint.CheckpointError`` or ``ValueError`` on bad input."""
    state = checkpoint.load(path)
    saved_env_id = state["args"]["env_id"]
    env_id = env_id or saved_env_id
    cli.register_goal_tasks()
    if env_id not in gym.registry:
        raise ValueError(f"unknown --env-id {env_id!r}: not a registered gymnasium id")
    if ROOT not in sys.path:
        sys.path.insert(0, ROOT)
    script = importlib.import_module(state["script"])
    raw_env, env = gym.make(env_id), script.make_env(env_id)()
    raw_spaces = raw_env.observation_space, raw_env.action_space
    obs_space, act_space = env.observation_space, env.action_space  # what the policy sees
    raw_env.close()
    env.close()
    if not isinstance(act_space, gym.spaces.Box):
        raise ValueError(f"{env_id} has {type(act_space).__name__} actions, the policy Box ones")
    act_dim = act_space.shape[0]
    if state["script"] == "ipg_her":
        goal_task = isinstance(obs_space, gym.spaces.Dict)
        obs_dim = obs_space["observation"].shape[0] if goal_task else obs_space.shape[0]
        goal_dim = obs_space["desired_goal"].shape[0] if goal_task else 0
        normalizer = InputNormalizer(obs_dim, goal_dim)
        agent = script.Agent(obs_dim + goal_dim, act_dim, hidden=state["args"]["hidden"])
        in_dim = obs_dim + goal_dim
    else:
        in_dim = obs_space.shape[0]
        normalizer = RunningMeanStd((in_dim,))
        agent = script.Agent(in_dim, act_dim)
    saved_in = state["agent"]["actor_mean.0.weight"].shape[1]
    saved_act = state["agent"]["actor_logstd"].shape[1]
    if (in_dim, act_dim) != (saved_in, saved_act):
        raise ValueError(
            f"{env_id} does not match the policy trained on {saved_env_id}: observation size "
            f"{in_dim} and action size {act_dim}, the policy's {saved_in} and {saved_act}"
        )
    agent.load_state_dict(state["agent"])
    normalizer.load_state_dict(state["normalizer" if state["script"] == "ipg_her" else "obs_rms"])
    return Policy(script, agent, normalizer, env_id, state, raw_spaces)


def _worker_init() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the training process's to handle
    torch.set_num_threads(1)


class BackgroundEvaluator:
    """Evaluations that run in a worker process while training goes on (``workers=1``), or at
    once in this process (``workers=0``): the results are the same, only the wall time differs.

    ``submit(step, evaluate, *args)`` runs ``evaluate(*args)`` on a deep copy of ``args`` taken
    now (a snapshot of the policy at ``step``); ``finished()`` returns the evaluations that are
    done, in the order they were submitted, as ``(step, result)``; ``finished(wait=True)`` waits
    for all of them. ``evaluate`` must be a module-level function (the worker imports it).
    """

    def __init__(self, workers: int):
        ctx = multiprocessing.get_context("spawn")  # no fork of a process running torch
        self.pool = ProcessPoolExecutor(workers, ctx, _worker_init) if workers > 0 else None
        self.pending = collections.deque()

    def submit(self, step: int, evaluate, *args) -> None:
        args = copy.deepcopy(args)
        if self.pool is None:
            future = Future()
            future.set_result(evaluate(*args))
        else:
            future = self.pool.submit(evaluate, *args)
        self.pending.append((step, future))

    def finished(self, wait: bool = False) -> list[tuple[int, object]]:
        done = []
        while self.pending and (wait or self.pending[0][1].done()):
            step, future = self.pending.popleft()
            done.append((step, future.result()))
        return done

    def close(self) -> None:
        """Stop the worker, dropping evaluations not yet finished."""
        if self.pool is not None:
            self.pool.shutdown(wait=False, cancel_futures=True)


def main(argv: list[str] | None = None) -> int:
    args = cli.parse_args(Args, argv)
    if args.episodes is not None and args.episodes <= 0:
        cli.fail(f"--episodes must be positive, got {args.episodes}")
    if args.seed is not None and args.seed < 0:
        cli.fail(f"--seed must be non-negative, got {args.seed}")
    try:
        policy = load_policy(args.path, args.env_id)
    except (checkpoint.CheckpointError, ValueError) as e:
        cli.fail(str(e))
    if args.seed is None and args.episodes in (None, len(policy.last_eval_seeds)):
        seeds = policy.last_eval_seeds  # replay the run's last evaluation
    else:
        episodes = args.episodes or len(policy.last_eval_seeds) or 10
        seeds = seeding.streams(args.seed or 0, 1).eval_seeds(episodes)
    if not seeds:
        cli.fail("the checkpoint holds no evaluation to replay; give --seed and --episodes")
    video_dir = None
    if args.capture_video:
        cli.check_video(policy.env_id)
        run_dir = args.path if os.path.isdir(args.path) else os.path.dirname(args.path)
        video_dir = os.path.join(run_dir, "videos", "evaluate")
    returns, successes = policy.evaluate(seeds, args.stochastic, video_dir)
    line = f"{len(returns)} episodes: return {returns.mean():.2f} ± {returns.std():.2f}"
    if len(successes):
        line += f", success rate {successes.mean():.2f}"
    print(line)
    if video_dir:
        print(f"videos in {video_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
