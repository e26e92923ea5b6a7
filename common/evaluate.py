"""Load, evaluate and watch a saved policy of any of the three scripts.

    python -m common.evaluate runs/FetchReach-v4__ipg_her__1__1795420633      # its model.pt
    python -m common.evaluate runs/.../model.pt --episodes 50 --seed 7 --capture-video
    python -m common.evaluate runs/.../resume.pt    # a run without --save-model: its resume point

From Python (a notebook), on raw environment observations (a Dict on goal tasks):

    policy = load_policy("runs/.../model.pt")
    action = policy(obs)

The policy is rebuilt from the file alone (``common/checkpoint.py``): the actor's weights (the
scripts' ``Agent``: a tanh MLP for the mean, a state-independent log std) and the normaliser
named by ``normalizer_class``, frozen as saved: ``InputNormalizer`` takes a goal Dict's
observation and desired goal apart, ``RunningMeanStd`` a flattened Dict. Training evaluates
through this same code, so without ``--seed`` the episodes are the ones the run's last
evaluation played, and a model.pt saved at a run's end prints that evaluation's mean return.
A model.pt saved mid-way (``--save-freq``, an interruption) holds newer weights than the
evaluated ones: the same episodes, not the same numbers.
"""

import os
import signal
import sys
from dataclasses import dataclass
from typing import Annotated

# isort: split
from common import cli  # first: Ctrl-C while torch loads is one line (cli.interrupted)

# isort: split
import gymnasium as gym
import numpy as np
import torch
import tyro

from common import checkpoint, seeding, tasks
from common.normalizer import InputNormalizer, RunningMeanStd


@dataclass
class Args:
    """Evaluate a saved policy: its mean return (and success rate) over episodes, optionally
    recorded as videos."""

    path: tyro.conf.Positional[Annotated[str, tyro.conf.arg(metavar="PATH")]]
    """a model.pt (--save-model), a resume.pt (--resume-freq), or the run folder holding one"""
    episodes: int | None = None
    """episodes to run (None: as many as the run's last evaluation)"""
    seed: int | None = None
    """seed of fresh evaluation episodes (None: replay the run's last evaluation's episodes)"""
    stochastic: bool = False
    """sample actions from the Gaussian policy instead of taking its mean"""
    capture_video: bool = False
    """record the first episode into the run's videos/evaluate (moviepy; MuJoCo's renderer)"""
    env_id: str | None = None
    """evaluate on another task with the same observation and action spaces"""


SUCCESS_KEYS = ("is_success", "success")  # a goal task's success flag: Fetch's, the mazes'


def success_of(info: dict):
    """A goal task's success flag in an episode's last ``info``, else None."""
    return next((info[key] for key in SUCCESS_KEYS if key in info), None)


LAYERS = {"Linear": torch.nn.Linear, "Tanh": torch.nn.Tanh, "ReLU": torch.nn.ReLU}  # buildable


def network(kinds: list[str] | None, weights: dict, name: str) -> torch.nn.Sequential:
    """The ``nn.Sequential`` a script saved as ``name``, rebuilt from its layer kinds (data,
    ``checkpoint.layers``; only ``LAYERS``) and its weights, so that its forward pass is the
    script's own. Raises ``checkpoint.CheckpointError`` for anything else."""
    prefix = f"{name}."
    saved = {k.removeprefix(prefix): v for k, v in weights.items() if k.startswith(prefix)}
    bad = checkpoint.CheckpointError(
        f"the saved {name} (layers {kinds}) is not a network of {', '.join(LAYERS)} starting Linear"
    )
    if not kinds or not set(kinds) <= LAYERS.keys() or kinds[0] != "Linear":
        raise bad
    try:
        layers = [
            LAYERS[kind]()
            if kind != "Linear"
            else torch.nn.utils.skip_init(torch.nn.Linear, *saved[f"{i}.weight"].shape[::-1])
            for i, kind in enumerate(kinds)
        ]
        net = torch.nn.Sequential(*layers)
        net.load_state_dict(saved)  # strict: the weights the layers need, and no other
    except (KeyError, RuntimeError) as e:
        raise bad from e
    return net.eval()


class Policy:
    """A saved policy as a function of a raw environment observation: ``action = policy(obs)``."""

    def __init__(self, content: dict, env_id: str):
        self.env_id, self.args = env_id, content["args"]
        self.last_eval_seeds = content["last_eval_seeds"]
        saved = content["normalizer"]
        if content["normalizer_class"] == "InputNormalizer":
            self.normalizer = InputNormalizer(len(saved["obs_rms"]["mean"]), len(saved["goal_rms"]["mean"]))
        else:
            self.normalizer = RunningMeanStd(np.shape(saved["mean"]))
        self.normalizer.load_state_dict(saved)
        kinds = content.get("agent_layers", {}).get("actor_mean")
        self.actor_mean = network(kinds, content["agent"], "actor_mean")  # the script's mu_theta
        self.log_std = content["agent"]["actor_logstd"]
        tasks.register_goal_tasks()
        env = gym.make(env_id)
        self.obs_space, action_space = env.observation_space, env.action_space
        env.close()
        self.low, self.high = action_space.low, action_space.high
        spaces = getattr(self.obs_space, "spaces", {"observation": self.obs_space})
        in_dim = gym.spaces.flatdim(self.obs_space)  # a goal Dict flattened, or a vector
        if isinstance(self.normalizer, InputNormalizer):  # observation and desired goal
            keys = [k for k in ("observation", "desired_goal") if k in spaces]
            in_dim = sum(gym.spaces.flatdim(spaces[k]) for k in keys)
        goals = tasks.goal_space(self.obs_space)
        if isinstance(self.normalizer, InputNormalizer) and self.normalizer.goal_task != goals:
            takes = "a goal Dict" if self.normalizer.goal_task else "a vector"
            raise ValueError(
                f"{env_id} does not match the policy trained on {self.args.get('env_id')}: the "
                f"policy takes {takes} as its observation, {env_id} gives "
                f"{'a goal Dict' if goals else 'a vector'}"
            )
        saved = (self.actor_mean[0].in_features, self.log_std.shape[1])
        if (in_dim, action_space.shape[0]) != saved:
            raise ValueError(
                f"{env_id} does not match the policy trained on {self.args.get('env_id')}: "
                f"input size {in_dim} and action size {action_space.shape[0]}, the policy's "
                f"{saved[0]} and {saved[1]}"
            )

    def inputs(self, obs) -> torch.Tensor:
        if isinstance(self.normalizer, InputNormalizer):
            return self.normalizer(obs)[None]
        flat = gym.spaces.flatten(self.obs_space, obs) if isinstance(obs, dict) else obs
        return self.normalizer(flat[None])

    def __call__(self, obs, stochastic: bool = False) -> np.ndarray:
        x = self.inputs(obs)
        with torch.no_grad():
            x = self.actor_mean(x)
            if stochastic:
                x = torch.normal(x, self.log_std.expand_as(x).exp())
        return np.clip(x.numpy()[0], self.low, self.high)

    def evaluate(self, seeds: list[int], stochastic=False, video_dir=None, video_episodes=1):
        """One episode per reset seed: the episodic returns and, on goal tasks, the successes
        (its success flag at the end). ``video_dir``: record the first ``video_episodes``."""
        env = gym.make(self.env_id, **{"render_mode": "rgb_array"} if video_dir else {})
        if video_dir:
            follow_camera(env)
            env = gym.wrappers.RecordVideo(env, video_dir, lambda e: e < video_episodes, disable_logger=True)
        env = gym.wrappers.RecordEpisodeStatistics(env)
        returns, successes = [], []
        for seed in seeds:
            obs, _ = env.reset(seed=seed)
            done = False
            while not done:
                obs, _, terminated, truncated, info = env.step(self(obs, stochastic))
                done = terminated or truncated
            returns.append(info["episode"]["r"])
            if (success := success_of(info)) is not None:
                successes.append(success)
        env.close()
        return np.array(returns, np.float64), np.array(successes, np.float64)


def follow_camera(env) -> None:
    """A MuJoCo task whose model has a tracking camera (``track``: Hopper, Walker2d, ...) is
    recorded through it; the default camera stays put and the runner leaves its view."""
    unwrapped = env.unwrapped
    if hasattr(unwrapped, "mujoco_renderer") and hasattr(unwrapped, "model"):
        import mujoco

        camera = mujoco.mj_name2id(unwrapped.model, mujoco.mjtObj.mjOBJ_CAMERA, "track")
        if camera >= 0:
            unwrapped.mujoco_renderer.camera_id = camera


def evaluate_snapshot(snapshot: dict, env_id: str, seeds: list[int], video_dir=None):
    """Training's evaluation: the deterministic policy of a snapshot ``checkpoint.state``."""
    policy = Policy(snapshot | {"args": {}, "last_eval_seeds": []}, env_id)
    return policy.evaluate(seeds, video_dir=video_dir)


def load_policy(path: str, env_id: str | None = None) -> Policy:
    """The policy saved at ``path`` (``checkpoint.load``'s), on its own task or on ``env_id``,
    another whose spaces match. A model file never chooses code to import: a task of a user's
    module (``module:Task-v0``) is made only when ``env_id`` names it. Raises
    ``checkpoint.CheckpointError`` or ``ValueError`` on bad input."""
    content = checkpoint.load(path)
    if env_id is None:
        env_id = str(content["args"].get("env_id", ""))
        if ":" in env_id:
            raise ValueError(
                f"this policy was trained on {env_id}; pass --env-id {env_id} to import {env_id.rpartition(':')[0]}"
            )
    tasks.register_goal_tasks()
    if why := tasks.task_refusal(env_id):
        raise ValueError(why)
    try:
        return Policy(content, env_id)
    except KeyError as e:  # a part the file should hold and does not
        raise checkpoint.CheckpointError(f"{path} lacks {e}: it is not a whole model.pt or resume.pt of these scripts") from e


def main(argv: list[str] | None = None) -> int:
    args = cli.parse_args(Args, argv, prog="python -m common.evaluate")
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


def stop(signum, frame):
    raise KeyboardInterrupt(signum)  # kill ends an evaluation as Ctrl-C does


if __name__ == "__main__":
    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGHUP, stop)
    try:
        sys.exit(main())
    except KeyboardInterrupt as e:  # one line, the shell's exit code: 130 (Ctrl-C), 143 (kill)
        print(cli.INTERRUPTED, file=sys.stderr)
        sys.exit(128 + (e.args[0] if e.args else signal.SIGINT))
