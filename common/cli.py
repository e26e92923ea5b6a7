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


def check_common(args) -> None:
    """The checks every script needs: a registered task, positive sizes, a budget of at least one
    batch that splits into minibatches, gamma and lambda in range, and ``--capture-video``'s
    prerequisites."""
    if args.env_id not in gym.registry:
        fail(
            f"unknown --env-id {args.env_id!r}; "
            "use a registered gymnasium id such as Hopper-v5 or FetchReach-v4"
        )
    check_positive(args, "total_timesteps", "num_envs", "num_steps", "num_minibatches")
    check_positive(args, "update_epochs", "eval_episodes")
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


def start_run(args) -> tuple[str, SummaryWriter]:
    """The run folder ``{log_dir}/{env_id}__{exp_name}__{seed}__{unix time}``, its TensorBoard
    writer with the hyperparameters as a text table (as CleanRL does), and SIGTERM turned into
    the KeyboardInterrupt of Ctrl-C, so that ``kill`` ends a run cleanly too."""
    run_name = f"{args.env_id}__{args.exp_name}__{args.seed}__{int(time.time())}"
    run_dir = os.path.join(args.log_dir, run_name)
    writer = SummaryWriter(run_dir)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    table = "\n".join(f"|{key}|{value}|" for key, value in vars(args).items())
    writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
    return run_dir, writer
