"""The command-line shell every script shares, so that the scripts hold only their algorithms.

Nothing here is about reinforcement learning: parsing an ``Args`` dataclass with tyro, and
refusing bad input with one ``error:`` line before any training starts (and before any run
folder exists). A check either returns or exits through ``fail``; it never changes ``args``.
"""

import contextlib
import difflib
import io
import os
import re
import sys
from typing import NoReturn, TypeVar

import gymnasium as gym
import numpy as np
import tyro

from common import grasped_start
from common.her import hindsight_refusal

A = TypeVar("A")


def register_goal_tasks() -> None:
    """Register the gymnasium-robotics tasks (FetchReach-v4, ...) without the notice its import
    prints about Adroit tasks we never use. MuJoCo loads the renderer ``MUJOCO_GL`` names on
    import, so a missing one is refused here, though training renders nothing."""
    try:
        import mujoco  # noqa: F401
    except Exception as e:
        if "MUJOCO_GL" not in os.environ:
            raise
        fail(f"MUJOCO_GL={os.environ['MUJOCO_GL']}: MuJoCo cannot load that renderer "
             f"({type(e).__name__}); install it (osmesa: apt install libosmesa6) or unset "
             "MUJOCO_GL, which only --capture-video needs")  # fmt: skip
    with contextlib.redirect_stderr(io.StringIO()):
        import gymnasium_robotics
    gym.register_envs(gymnasium_robotics)


def fail(message: str) -> NoReturn:
    """Bad input: one clear line, no traceback, non-zero exit."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def parse_args(args_class: type[A], argv: list[str] | None = None, prog: str | None = None,
               task_defaults: dict | None = None) -> A:  # fmt: skip
    """``tyro.cli``, with a parse error reduced to one line (tyro draws a box). ``task_defaults``
    ``{env_id: {field: value}}``: the task's own defaults, for the fields not given in ``argv``;
    one line says which were taken."""
    captured, argv = io.StringIO(), sys.argv[1:] if argv is None else argv
    try:
        with contextlib.redirect_stderr(captured):
            args = tyro.cli(args_class, args=argv, prog=prog)
        given = {re.sub(r"^--no-", "--", a.split("=")[0]) for a in argv}  # --no-x gives x
        own = {k: v for k, v in (task_defaults or {}).get(args.env_id, {}).items()
               if flag(k) not in given}  # fmt: skip
        for name, value in own.items():
            setattr(args, name, value)
        if own:
            typed = {k: " ".join(map(str, np.atleast_1d(v))) for k, v in own.items()}  # tuples too
            spelled = [flag(k) if v is True else f"{flag(k)} {typed[k]}" for k, v in own.items()]
            print(f"{args.env_id}'s own defaults: {', '.join(spelled)}", flush=True)  # as typed
        return args
    except SystemExit as e:
        if e.code:
            text = " ".join(re.sub(r"[│╭╮╰╯─]|-{3,}", " ", captured.getvalue()).split())
            if "Unrecognized options:" in text:  # tyro's headings and each guess's help: one line
                rest = text.split("Unrecognized options:", 1)[1]
                given = re.split(r" (?:Perhaps|Arguments similar|For full)", rest, maxsplit=1)[0]
                guesses = re.findall(r"(?:meant|similar to --[\w-]+): (--[\w-]+)", rest)
                guess = f"; did you mean {' or '.join(guesses)}?" if guesses else ""
                fail(f"unrecognized option {given.strip()}{guess} (--help lists them)")
            fail(text)
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
    check_positive(args, "num_envs")
    goal_task = check_task(args.env_id, args.num_envs)
    check_positive(args, "total_timesteps", "num_steps", "num_minibatches")
    check_positive(args, "update_epochs", "eval_episodes", "learning_rate")
    if args.seed < 0:
        fail(f"--seed must be non-negative, got {args.seed}")
    for name in ("save_freq", "eval_freq", "eval_workers", "resume_freq"):
        if getattr(args, name) < 0:
            fail(f"{flag(name)} must be non-negative (0 turns it off), got {getattr(args, name)}")
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


def refuse_ignored(argv: list[str], ignored: dict[str, str]) -> None:
    """A flag given on the command line that would change nothing fails: ``{flag: why}``."""
    for flag in (a.split("=")[0] for a in argv):
        if flag in ignored:
            fail(f"{flag} would be ignored ({ignored[flag]}): leave it out")


def check_her(args, argv: list[str], goal_task: bool) -> None:
    """IPG's flags that would be ignored (HER's without goals or with --no-her, the replay batch
    size with on-policy states, the penalties, twin critic and critic target at nu = 0) are refused,
    and so are nu outside [0, 1], a negative penalty, a target sigma not positive or not one per
    action dimension, a non-positive replay batch, HER on a task it cannot serve, and grasped
    starts outside [0, 1] or where nothing can be grasped."""
    if not 0.0 <= args.nu <= 1.0 or args.her_n_sampled_goal < 0:
        fail(f"--nu must be in [0, 1] (got {args.nu}) and --her-n-sampled-goal non-negative")
    check_positive(args, "off_policy_batch_size")
    her_flags = ("--her-n-sampled-goal", "--her-goal-selection-strategy")
    ignored = dict.fromkeys(her_flags, "--no-her") if not args.her else {}  # flag: why ignored
    if not goal_task:
        ignored = dict.fromkeys(("--her", *her_flags), f"{args.env_id} is not a goal task")
    if args.off_policy_states == "batch":
        ignored["--off-policy-batch-size"] = "--off-policy-states batch"
    if args.nu == 0 and not args.use_cv:
        penalties = ("--action-l2", "--bounds-loss", "--twin-critic", "--critic-target")
        ignored |= dict.fromkeys(penalties, "no off-policy term at nu = 0")
    refuse_ignored(argv, ignored)
    stds = () if args.target_std is None else tuple(np.atleast_1d(args.target_std))
    if min(args.action_l2, args.bounds_loss) < 0 or min(stds, default=1.0) <= 0:
        fail("--action-l2 and --bounds-loss must be non-negative and --target-std positive")
    if len(stds) > 1 and len(stds) != (dims := gym.make(args.env_id).action_space.shape[0]):
        fail(f"--target-std takes one sigma or one per action dimension ({dims} on "
             f"{args.env_id}), not {len(stds)}")  # fmt: skip
    if goal_task and args.her and (why := hindsight_refusal(args.env_id)):
        fail(why)
    if not 0.0 <= args.grasped_start <= 1.0:
        fail(f"--grasped-start is a share of the episodes, in [0, 1]; got {args.grasped_start}")
    if args.grasped_start and (why := grasped_start.refusal(args.env_id)):
        fail(why)


def check_critic(args) -> None:
    """The checks of an off-policy critic's settings (Q-Prop's and IPG's)."""
    check_positive(args, "critic_batch_size", "buffer_size", "critic_learning_rate")
    check_positive(args, *(name for name in ("hidden", "critic_hidden") if hasattr(args, name)))
    if not 0.0 < args.tau <= 1.0:
        fail(f"--tau must be in (0, 1], got {args.tau}")
    if args.critic_steps < 0 or args.learning_starts < 0:
        fail("--critic-steps and --learning-starts must be non-negative")
    rows, longest = args.buffer_size // args.num_envs, gym.spec(args.env_id).max_episode_steps
    if longest and rows < longest:  # replay samples finished episodes only
        fail(f"--buffer-size {args.buffer_size} keeps {rows} steps per env, less than one "
             f"{args.env_id} episode ({longest} steps); enlarge it")  # fmt: skip


def check_task(env_id: str, num_envs: int = 1) -> bool:
    """The task is registered, its dependencies are installed, ``num_envs`` copies of its
    simulator fit in the free memory, its actions are continuous and its observations a vector
    or a goal Dict (``observation``, ``achieved_goal``, ``desired_goal``, each a vector).
    Returns whether it is a goal task."""
    if env_id not in gym.registry:
        close = difflib.get_close_matches(env_id, gym.registry, n=1)
        hint = f"did you mean {close[0]}?" if close else "use a registered id such as Hopper-v5"
        fail(f"unknown --env-id {env_id!r}; {hint}")
    try:
        env = gym.make(env_id)
    except gym.error.DependencyNotInstalled as e:
        if "mujoco_py" in str(e):
            fail(f"{env_id} needs the deprecated mujoco-py, which this project does not support; "
                 "use a v4 or v5 MuJoCo task such as Hopper-v5")  # fmt: skip
        fail(f"{env_id} needs a dependency that is not installed: {' '.join(map(str, e.args))}")
    action_space, observation_space = env.action_space, env.observation_space
    if (model := getattr(env.unwrapped, "model", None)) is not None:  # a MuJoCo task
        need = num_envs * (model.nbuffer + env.unwrapped.data.nbuffer + env.unwrapped.data.narena)
        free = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        if need > free:
            fail(f"--num-envs {num_envs}: {num_envs} copies of {env_id}'s simulator need about "
                 f"{need / 2**30:.1f} GiB, and {free / 2**30:.1f} GiB are free")  # fmt: skip
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
