"""The command-line shell every script shares, so that the scripts hold only their algorithms.

Nothing here is about reinforcement learning: parsing an ``Args`` dataclass with tyro, and
refusing bad input with one ``error:`` line before any training starts (and before any run
folder exists). A check either returns or exits through ``fail``; it never changes ``args``.
"""

import contextlib
import dataclasses
import difflib
import importlib
import io
import math
import os
import re
import sys
import warnings
from collections.abc import Callable
from typing import NoReturn, TypeVar

INTERRUPTED = "interrupted; nothing was written"


def interrupted(kind, error, traceback) -> None:
    """``sys.excepthook``: Ctrl-C before a run is under way (imports, checks, loading a resume
    point) or an evaluation ends in one line instead of a traceback (the exit code stays Ctrl-C's,
    130); anything else as usual."""
    if issubclass(kind, KeyboardInterrupt):
        print(INTERRUPTED, file=sys.stderr)
    else:
        sys.__excepthook__(kind, error, traceback)


sys.excepthook = interrupted  # before the slow imports below

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import tyro  # noqa: E402

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
               task_defaults: Callable[[str], dict] | None = None,
               ignored: Callable[[A], dict[str, str]] | None = None) -> A:  # fmt: skip
    """``tyro.cli``, with a parse error reduced to one line (tyro draws a box). ``task_defaults``
    ``env_id -> {field: value}``: the task's own defaults, for the fields not given in ``argv``
    (in any spelling) nor ``ignored(args)`` (``{flag: why}``, the flags the run would ignore);
    one line says which were taken."""
    captured, argv = io.StringIO(), sys.argv[1:] if argv is None else argv
    try:
        with contextlib.redirect_stderr(captured):
            args = tyro.cli(args_class, args=argv, prog=prog)
    except SystemExit as e:
        if e.code:
            fail(parse_error(captured.getvalue()))
        raise
    skip = {flag(name) for name in given(argv)} | set(ignored(args) if ignored else ())
    own = task_defaults(args.env_id) if task_defaults else {}
    own = {k: v for k, v in own.items() if flag(k) not in skip}
    for name, value in own.items():
        setattr(args, name, value)
    if own:
        typed = {k: " ".join(map(str, np.atleast_1d(v))) for k, v in own.items()}  # tuples too
        spelled = [flag(k) if v is True else f"{flag(k)} {typed[k]}" for k, v in own.items()]
        print(f"defaults for {args.env_id}: {', '.join(spelled)}", flush=True)  # as typed
    return args


EXPECTS = {
    "INT": "an integer",
    "FLOAT": "a number",
    "{None}|FLOAT": "a number or None",
    "{None}|FLOAT|{[FLOAT [FLOAT ...]]}": "None, a number or several",
}  # tyro's metavars


def parse_error(box: str) -> str:
    """tyro's error box as one line: what the flag expects and what it got."""
    text = " ".join(re.sub(r"[│╭╮╰╯─]|-{3,}", " ", box).split())
    if m := re.search(r"Error parsing (--[\w-]+): (.*?) Argument helptext: --[\w-]+ (.*)", text):
        union = re.search(r"instantiated from \[(.*?)\]", m[2])  # a union's: every value
        quoted = re.findall(r"'(.*?)'", union[1] if union else m[2])
        value = " ".join(quoted if union else quoted[-1:])
        metavar = next((k for k in EXPECTS if m[3].startswith(f"{k} ")), m[3].split()[0])
        return f"{m[1]} expects {EXPECTS.get(metavar, metavar)}, got {value!r}"
    if m := re.search(r"invalid choice '(.*?)' for argument '(--[\w-]+)'\. Expected one of "
                      r"\((.*?)\)", text):  # fmt: skip
        choices = ", ".join(re.findall(r"'(.*?)'", m[3]))
        return f"{m[2]} expects one of ({choices}), got {m[1]!r}"
    if m := re.search(r"Missing value for argument '(--[\w-]+)'", text):
        return f"{m[1]} expects a value"
    if "Unrecognized options:" in text:  # tyro's headings and each guess's help: one line
        rest = text.split("Unrecognized options:", 1)[1]
        options = re.split(r" (?:Perhaps|Arguments similar|For full)", rest, maxsplit=1)[0]
        guesses = re.findall(r"(?:meant|similar to --[\w-]+): (--[\w-]+)", rest)
        guess = f"; did you mean {' or '.join(guesses)}?" if guesses else ""
        return f"unrecognized option {options.strip()}{guess} (--help lists them)"
    return re.sub(r" For full helptext.*", "", text)


def given(argv: list[str]) -> dict[str, str]:
    """The fields ``argv`` sets, whatever the spelling (``--a-b``, ``--a_b``, ``--a-b=1``,
    ``--no-a``, ``--no_a``): ``{field: flag as typed}``."""
    return {re.sub(r"^no_", "", a.split("=")[0][2:].replace("-", "_")): a.split("=")[0]
            for a in argv if a.startswith("--")}  # fmt: skip


def flag(name: str) -> str:
    """The command-line spelling of an ``Args`` field: ``num_envs`` -> ``--num-envs``."""
    return "--" + name.replace("_", "-")


def check_positive(args, *names: str) -> None:
    for name in names:
        if getattr(args, name) <= 0:
            fail(f"{flag(name)} must be positive, got {getattr(args, name)}")


def check_non_negative(args, *names: str) -> None:
    for name in names:
        if getattr(args, name) < 0:
            fail(f"{flag(name)} must be non-negative, got {getattr(args, name)}")


def check_range(args, name: str, low: float, high: float, open_low: bool = False) -> None:
    """``args.name`` in [low, high], or (low, high] with ``open_low``."""
    value = getattr(args, name)
    if not (low < value if open_low else low <= value) or value > high:
        fail(f"{flag(name)} must be in {'(' if open_low else '['}{low:g}, {high:g}], got {value}")


def check_finite(args) -> None:
    """Every float flag, and every float in a tuple flag, is a finite number (nan, inf: no)."""
    for field in dataclasses.fields(args):
        value = getattr(args, field.name)
        values = value if isinstance(value, tuple) else (value,)
        if any(isinstance(v, float) and not math.isfinite(v) for v in values):
            fail(f"{flag(field.name)} must be a finite number, got {' '.join(map(str, values))}")


def check_common(args) -> bool:
    """The checks every script needs: finite numbers, a task that exists and that these scripts
    can drive, positive sizes and learning rates, a budget of at least one batch that splits into
    minibatches, gamma and lambda in range, and ``--capture-video``'s prerequisites. Returns
    whether the task is a goal task."""
    check_finite(args)
    check_exp_name(args.exp_name)
    check_positive(args, "num_envs")
    goal_task = check_task(args.env_id, args.num_envs)
    check_positive(args, "total_timesteps", "num_steps", "num_minibatches", "torch_threads")
    check_positive(args, "update_epochs", "eval_episodes", "learning_rate", "kl_target")
    check_positive(args, "vf_coef", "max_grad_norm")  # <= 0: V unlearnt, reversed or frozen
    if args.save_freq and not args.save_model:
        fail(f"--save-freq {args.save_freq} would be ignored (it saves model.pt, which only "
             "--save-model writes): add --save-model or leave it out")  # fmt: skip
    for name in ("seed", "save_freq", "eval_freq", "eval_workers", "resume_freq", "beta_init"):
        if getattr(args, name) < 0:
            off = " (0 turns it off)" if name.endswith("freq") else ""
            fail(f"{flag(name)} must be non-negative{off}, got {getattr(args, name)}")
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
    check_range(args, "gamma", 0.0, 1.0, open_low=True)
    check_range(args, "gae_lambda", 0.0, 1.0)
    if args.capture_video:
        check_video(args.env_id)
    return goal_task


def check_exp_name(name: str) -> None:
    """The middle of a run folder's name ``{env_id}__{exp_name}__{seed}__{time}``: a path in it
    would put the folder outside --log-dir, under a name report.py cannot read."""
    if not name or "/" in name or "\0" in name:
        fail(f"--exp-name {name!r} must be a plain name, without '/'")


def refuse(why: str | None) -> None:
    """Fail with ``why``, the reason a module gives for refusing the input (None: no refusal)."""
    if why:
        fail(why)


def ignored(*rules: tuple[bool, str, str]) -> dict[str, str]:
    """``{flag: why}`` from the rules ``(when, "--flag --other-flag", why)`` that hold: the flags a
    run would ignore (a later rule's why wins)."""
    return {flag: why for when, flags, why in rules if when for flag in flags.split()}


def refuse_ignored(argv: list[str], ignored: dict[str, str]) -> None:
    """A flag given on the command line that would change nothing fails: ``{flag: why}``; any
    spelling of it (``--a_b``, ``--no-a``, ``--a=1``) too."""
    for name, typed in given(argv).items():
        if flag(name) in ignored:
            fail(f"{typed} would be ignored ({ignored[flag(name)]}): leave it out")


def current_version(env_id: str) -> str | None:
    """The highest registered version of ``env_id``'s task that constructs (FetchReach-v1:
    FetchReach-v4), or None."""
    try:
        namespace, name, _ = gym.envs.registration.parse_env_id(env_id)
    except gym.error.Error:
        return None
    specs = [s for s in gym.registry.values() if (s.namespace, s.name) == (namespace, name)]
    for spec in sorted(specs, key=lambda s: s.version or 0, reverse=True):
        try:
            with warnings.catch_warnings(action="ignore"):
                gym.make(spec.id).close()
            return spec.id
        except Exception:
            continue
    return None


def check_task(env_id: str, num_envs: int = 1) -> bool:
    """``task_refusal``'s checks, failing with its line. Returns whether it is a goal task."""
    refuse(task_refusal(env_id, num_envs))
    return goal_task(env_id)


def task_refusal(env_id: str, num_envs: int = 1) -> str | None:
    """Why ``env_id`` cannot serve, or None. The task is registered (by its module, imported
    first, for an id ``module:Task-v0``), its dependencies are installed, ``num_envs`` copies of
    its simulator fit in the available memory, it has a time limit, its actions are continuous,
    its observations a vector or a goal Dict (``GOAL_KEYS``, each a vector), and one reset
    returns observations of the shapes it declares."""
    try:
        name = import_task(env_id)
    except BaseException as e:  # a module that raises, even SystemExit: not ours to end on
        if isinstance(e, KeyboardInterrupt):
            raise
        return (f"--env-id {env_id}: cannot import {env_id.rpartition(':')[0]} "
                f"({type(e).__name__}: {e})")  # fmt: skip
    if name not in gym.registry:
        close = current_version(name) or next(iter(difflib.get_close_matches(
            name, gym.registry, n=1)), None)  # fmt: skip
        close = close and env_id.removesuffix(name) + close  # with its module, if it has one
        hint = f"did you mean {close}?" if close else "use a registered id such as Hopper-v5"
        return f"unknown --env-id {env_id!r}; {hint}"
    try:
        with warnings.catch_warnings(action="ignore"):  # an old version's: refused below
            env = gym.make(env_id)
    except gym.error.DependencyNotInstalled as e:
        if "mujoco_py" in str(e):
            current = current_version(name) or "a v4 or v5 MuJoCo task such as Hopper-v5"
            return (f"{env_id} needs the deprecated mujoco-py, which this project does not "
                    f"support; use {current}")  # fmt: skip
        return f"{env_id} needs a dependency that is not installed: {' '.join(map(str, e.args))}"
    except Exception as e:
        return f"--env-id {env_id}: making the task failed ({type(e).__name__}: {e})"
    try:
        return _env_refusal(env, env_id, num_envs)
    finally:
        env.close()


def _env_refusal(env: gym.Env, env_id: str, num_envs: int) -> str | None:
    """``task_refusal``'s checks of a made environment."""
    if env.spec.max_episode_steps is None:  # the replay and the evaluation wait for ends
        return (f"{env_id} has no time limit: register it with max_episode_steps, so that its "
                "episodes end")  # fmt: skip
    action_space, observation_space = env.action_space, env.observation_space
    if (model := getattr(env.unwrapped, "model", None)) is not None:  # a MuJoCo task
        need = num_envs * (model.nbuffer + env.unwrapped.data.nbuffer + env.unwrapped.data.narena)
        if need > (free := available_memory()):
            return (f"--num-envs {num_envs}: {num_envs} copies of {env_id}'s simulator need "
                    f"about {need / 2**30:.1f} GiB, and {free / 2**30:.1f} GiB are "
                    "free")  # fmt: skip
    if not isinstance(action_space, gym.spaces.Box):
        return (f"{env_id} has {type(action_space).__name__} actions; these scripts need "
                "continuous (Box) actions, e.g. Hopper-v5, FetchReach-v4")  # fmt: skip
    if not (isinstance(observation_space, gym.spaces.Box) or goal_space(observation_space)):
        return (f"{env_id}'s observations are not supported: a vector (Box) or a goal Dict with "
                f"vector {', '.join(GOAL_KEYS)} are")  # fmt: skip
    with warnings.catch_warnings(action="ignore"):
        obs, _ = env.reset(seed=0)
    boxes = observation_space.spaces if goal_space(observation_space) else {"": observation_space}
    for key, box in boxes.items():
        got = np.shape(obs[key] if key else obs)
        if key in GOAL_KEYS + ("",) and got != box.shape:
            what = f"observation {key!r}" if key else "observation"
            return (f"{env_id}'s reset returns an {what} of shape {got}, its observation space "
                    f"declares {box.shape}: make them agree")  # fmt: skip
    return None


def available_memory() -> int:
    """Bytes of memory available to a new allocation (Linux's MemAvailable, else free pages)."""
    try:
        with open("/proc/meminfo") as f:
            line = next(line for line in f if line.startswith("MemAvailable:"))
        return 1024 * int(line.split()[1])
    except (OSError, StopIteration):
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def check_memory(nbytes: float, what: str) -> None:
    """Fail if ``what`` (a flag and its value) would need more than the available memory: an
    allocation the machine cannot serve, refused before the run rather than a traceback in it."""
    if nbytes > (free := available_memory()):
        fail(f"{what} needs about {nbytes / 2**30:,.1f} GiB of memory, and "
             f"{free / 2**30:.1f} GiB are available; make it smaller")  # fmt: skip


GOAL_KEYS = ("observation", "achieved_goal", "desired_goal")


def task_name(env_id: str) -> str:
    """The id gymnasium registered: ``Task-v0`` for gymnasium's ``module:Task-v0``, else the id."""
    return env_id.rpartition(":")[2]


def import_task(env_id: str) -> str:
    """``task_name(env_id)``, once the module of a ``module:Task-v0`` is imported (it registers
    the task as it is imported)."""
    if ":" in env_id:
        importlib.import_module(env_id.rpartition(":")[0])
    return task_name(env_id)


def goal_space(space: gym.Space) -> bool:
    """A goal task's observations: a Dict of vectors ``GOAL_KEYS`` (gymnasium-robotics' GoalEnv)."""
    boxes = [space.spaces.get(k) for k in GOAL_KEYS] if isinstance(space, gym.spaces.Dict) else []
    return bool(boxes) and all(isinstance(b, gym.spaces.Box) and len(b.shape) == 1 for b in boxes)


def goal_task(env_id: str) -> bool:
    """Whether ``env_id`` is a goal task; False where it cannot be made (``check_task``: why)."""
    try:
        with warnings.catch_warnings(action="ignore"), contextlib.redirect_stderr(io.StringIO()):
            env = gym.make(env_id)
    except Exception:
        return False
    env.close()
    return goal_space(env.observation_space)


def check_video(env_id: str) -> None:
    """``--capture-video`` needs moviepy and a renderer: try both before training starts."""
    with warnings.catch_warnings(action="ignore"):
        modes = gym.make(env_id).metadata.get("render_modes", [])
    if "rgb_array" not in modes:
        fail(f"--capture-video: {env_id} renders no rgb_array frames (render_modes {modes})")
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
