"""The command-line shell every script shares, so that the scripts hold only their algorithms.

Nothing here is about reinforcement learning: parsing an ``Args`` dataclass with tyro, refusing
bad input with one ``error:`` line before any training starts, the checks every script needs,
the run folder and its TensorBoard writer, and a ``kill`` that ends a run as Ctrl-C does.
A check either returns or exits through ``fail``; it never changes ``args``.
"""

import contextlib
import io
import os
import re
import signal
import sys
import time
from typing import NoReturn, TypeVar

import gymnasium as gym
import tyro
from torch.utils.tensorboard import SummaryWriter

A = TypeVar("A")


def register_goal_tasks() -> None:
    """Register the gymnasium-robotics tasks (FetchReach-v4, ...) without the notice its import
    prints about Adroit tasks we never use."""
    with contextlib.redirect_stderr(io.StringIO()):
        import gymnasium_robotics
    gym.register_envs(gymnasium_robotics)


def fail(message: str) -> NoReturn:
    """Bad input: one clear line, no traceback, non-zero exit."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def parse_args(args_class: type[A], argv: list[str] | None = None) -> A:
    """``tyro.cli``, with a parse error reduced to one line (tyro draws a box)."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            return tyro.cli(args_class, args=argv)
    except SystemExit as e:
        if e.code:
            fail(" ".join(re.sub(r"[│╭╮╰╯─]", " ", captured.getvalue()).split()))
        raise


def flag(name: str) -> str:
    """The command-line spelling of an ``Args`` field: ``num_envs`` -> ``--num-envs``."""
    return "--" + name.replace("_", "-")


def check_positive(args, *names: str) -> None:
    for name in names:
        if getattr(args, name) <= 0:
            fail(f"{flag(name)} must be positive, got {getattr(args, name)}")


def check_common(args) -> bool:
    """The checks every script needs: a task that exists and that these scripts can drive,
    positive sizes and learning rates, a budget of at least one batch that splits into
    minibatches, gamma and lambda in range, and ``--capture-video``'s prerequisites. Returns
    whether the task is a goal task."""
    goal_task = check_task(args.env_id)
    check_positive(args, "total_timesteps", "num_envs", "num_steps", "num_minibatches")
    check_positive(args, "update_epochs", "eval_episodes", "learning_rate")
    if args.seed < 0:
        fail(f"--seed must be non-negative, got {args.seed}")
    if args.save_freq < 0:
        fail(f"--save-freq must be non-negative (0: save only at the end), got {args.save_freq}")
    batch_size = args.num_envs * args.num_steps
    if args.total_timesteps < batch_size:
        fail(
            f"--total-timesteps {args.total_timesteps} is less than one batch "
            f"(num_envs * num_steps = {batch_size})"
        )
    if batch_size % args.num_minibatches:
        fail(
            f"batch {batch_size} (num_envs * num_steps) does not split into "
            f"{args.num_minibatches} minibatches; change --num-minibatches"
        )
    if not 0 < args.gamma <= 1 or not 0 <= args.gae_lambda <= 1:
        fail("--gamma must be in (0, 1] and --gae-lambda in [0, 1]")
    if args.kl_target <= 0 or args.beta_init < 0:
        fail("--kl-target must be positive and --beta-init non-negative")
    if args.capture_video:
        check_video(args.env_id)
    return goal_task


def check_task(env_id: str) -> bool:
    """The task is registered, its dependencies are installed, its actions are continuous and
    its observations a vector or a goal Dict (``observation``, ``achieved_goal``,
    ``desired_goal``, each a vector). Returns whether it is a goal task."""
    if env_id not in gym.registry:
        fail(f"unknown --env-id {env_id!r}; use a registered id such as Hopper-v5 or FetchReach-v4")
    try:
        env = gym.make(env_id)
    except gym.error.DependencyNotInstalled as e:
        if "mujoco_py" in str(e):
            fail(f"{env_id} needs the deprecated mujoco-py, which this project does not support; "
                 "use a v4 or v5 MuJoCo task such as Hopper-v5")  # fmt: skip
        fail(f"{env_id} needs a dependency that is not installed: {' '.join(map(str, e.args))}")
    action_space, observation_space = env.action_space, env.observation_space
    env.close()
    if not isinstance(action_space, gym.spaces.Box):
        fail(f"{env_id} has {type(action_space).__name__} actions; these scripts need continuous "
             "(Box) actions, e.g. Hopper-v5, FetchReach-v4")  # fmt: skip
    goal_keys = ("observation", "achieved_goal", "desired_goal")
    goal_task = isinstance(observation_space, gym.spaces.Dict) and all(
        isinstance(observation_space.spaces.get(k), gym.spaces.Box) for k in goal_keys
    )
    if not (isinstance(observation_space, gym.spaces.Box) or goal_task):
        fail(f"{env_id}'s observations are not supported: a vector (Box) or a goal Dict with "
             f"vector {', '.join(goal_keys)} are")  # fmt: skip
    return goal_task


def check_video(env_id: str) -> None:
    """``--capture-video`` needs moviepy and a renderer: try both before training starts."""
    try:
        import moviepy  # noqa: F401

        env = gym.make(env_id, render_mode="rgb_array")
        env.reset(seed=0)
        env.render()
        env.close()
    except ImportError:
        fail("--capture-video needs moviepy: pip install moviepy")
    except Exception as e:
        fail(
            f"--capture-video: rendering {env_id} failed ({type(e).__name__}); MuJoCo needs an "
            "OpenGL backend, e.g. apt install libosmesa6 and MUJOCO_GL=osmesa"
        )


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``), raised like Ctrl-C's KeyboardInterrupt so that a run ends cleanly."""


def raise_terminated(signum, frame) -> NoReturn:
    raise Terminated()


def exit_code(interrupt: KeyboardInterrupt) -> int:
    """The shell's convention: 128 + the signal's number (143 for SIGTERM, 130 for Ctrl-C)."""
    return 128 + (signal.SIGTERM if isinstance(interrupt, Terminated) else signal.SIGINT)


def start_run(args) -> tuple[str, SummaryWriter]:
    """A new run folder ``{log_dir}/{env_id}__{exp_name}__{seed}__{unix time}`` (a suffix keeps
    two runs started in the same second apart), its TensorBoard writer with the hyperparameters
    as a text table (as CleanRL does), and SIGTERM turned into a KeyboardInterrupt like Ctrl-C's,
    so that ``kill`` ends a run cleanly too."""
    run_name = f"{args.env_id}__{args.exp_name}__{args.seed}__{int(time.time())}"
    run_dir = os.path.join(args.log_dir, run_name)
    for suffix in range(1, 1000):
        try:
            os.makedirs(run_dir)
            break
        except FileExistsError:
            run_dir = os.path.join(args.log_dir, f"{run_name}-{suffix}")
        except OSError as e:
            fail(f"cannot create the run folder in --log-dir {args.log_dir!r}: {e.strerror}")
    print(f"run folder: {run_dir}", flush=True)
    writer = SummaryWriter(run_dir)
    signal.signal(signal.SIGTERM, raise_terminated)
    table = "\n".join(f"|{key}|{value}|" for key, value in vars(args).items())
    writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
    return run_dir, writer


def resume_run(run_dir: str, step: int) -> tuple[str, SummaryWriter]:
    """Go on logging into an existing run folder after ``step``: TensorBoard drops the events an
    interrupted run wrote after its last resume point (``purge_step``: from step + 1 on), so no
    step is logged twice."""
    print(f"resuming run folder: {run_dir} after step {step:,}", flush=True)
    signal.signal(signal.SIGTERM, raise_terminated)
    return run_dir, SummaryWriter(run_dir, purge_step=step + 1)


class Progress:
    """A live line (steps done of total, steps/s, ETA, the latest training figure), redrawn in
    place when standard output is a terminal and silent when it is not (CI, the benchmark
    runner's logs); ``print`` writes a message above it, ``close`` the closing summary."""

    def __init__(self, total_steps: int):
        self.total, self.live, self.start = total_steps, sys.stdout.isatty(), time.time()

    def update(self, step: int, sps: int, latest: str = "") -> None:
        if self.live:
            eta = (self.total - step) / max(sps, 1)
            line = f"{step:,}/{self.total:,} steps  {sps:,} steps/s  ETA {eta:.0f} s  {latest}"
            print(f"\r\033[K{line}", end="", flush=True)

    def print(self, message: str, file=None) -> None:
        if self.live:
            print("\r\033[K", end="", flush=True)
        print(message, file=file or sys.stdout, flush=True)

    def close(self, steps: int, eval_returns, eval_success) -> None:
        summary = f"done: {steps:,} steps in {time.time() - self.start:.0f} s"
        if len(eval_returns):
            summary += f"; last evaluation: return {eval_returns.mean():.1f}"
        if len(eval_success):
            summary += f", success {eval_success.mean():.2f}"
        self.print(summary)
