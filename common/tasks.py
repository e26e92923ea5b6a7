"""Which tasks these scripts can drive: registering gymnasium-robotics' tasks, and why a task
cannot serve (``task_refusal``: its module, its id, its dependencies, its spaces, its memory;
``video_refusal``: its frames). Nothing here ends the process: ``common/cli.py`` turns a reason
into the one ``error:`` line.
"""

import contextlib
import difflib
import importlib
import io
import os
import sys
import warnings

import gymnasium as gym
import numpy as np


def register_goal_tasks() -> None:
    """Register the gymnasium-robotics tasks (FetchReach-v4, ...) without the notice its import
    prints about Adroit tasks we never use. MuJoCo loads the renderer ``MUJOCO_GL`` names on
    import, so a missing one is refused here, though training renders nothing."""
    try:
        import mujoco  # noqa: F401
    except Exception as e:
        if "MUJOCO_GL" not in os.environ:
            raise
        print(
            f"error: MUJOCO_GL={os.environ['MUJOCO_GL']}: MuJoCo cannot load that renderer "
            f"({type(e).__name__}); install it (osmesa: apt install libosmesa6) or unset "
            "MUJOCO_GL, which only --capture-video needs",
            file=sys.stderr,
        )
        sys.exit(2)
    with contextlib.redirect_stderr(io.StringIO()):
        import gymnasium_robotics
    gym.register_envs(gymnasium_robotics)


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
        return f"--env-id {env_id}: cannot import {env_id.rpartition(':')[0]} ({type(e).__name__}: {e})"
    if name not in gym.registry:
        close = current_version(name) or next(iter(difflib.get_close_matches(name, gym.registry, n=1)), None)
        close = close and env_id.removesuffix(name) + close  # with its module, if it has one
        hint = f"did you mean {close}?" if close else "use a registered id such as Hopper-v5"
        return f"unknown --env-id {env_id!r}; {hint}"
    try:
        with warnings.catch_warnings(action="ignore"):  # an old version's: refused below
            env = gym.make(env_id)
    except gym.error.DependencyNotInstalled as e:
        if "mujoco_py" in str(e):
            current = current_version(name) or "a v4 or v5 MuJoCo task such as Hopper-v5"
            return f"{env_id} needs the deprecated mujoco-py, which this project does not support; use {current}"
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
        return f"{env_id} has no time limit: register it with max_episode_steps, so that its episodes end"
    action_space, observation_space = env.action_space, env.observation_space
    if (model := getattr(env.unwrapped, "model", None)) is not None:  # a MuJoCo task
        need = num_envs * (model.nbuffer + env.unwrapped.data.nbuffer + env.unwrapped.data.narena)
        if need > (free := available_memory()):
            return (
                f"--num-envs {num_envs}: {num_envs} copies of {env_id}'s simulator need "
                f"about {need / 2**30:.1f} GiB, and {free / 2**30:.1f} GiB are "
                "free"
            )
    if not isinstance(action_space, gym.spaces.Box):
        return (
            f"{env_id} has {type(action_space).__name__} actions; these scripts need "
            "continuous (Box) actions, e.g. Hopper-v5, FetchReach-v4"
        )
    for what, shape in (("actions", action_space.shape), ("observations", observation_space.shape)):
        if shape is not None and len(shape) != 1:  # the networks and the Gaussian take vectors
            return f"{env_id}'s {what} have shape {shape}; these scripts need vectors (1-D Boxes)"
    if not (isinstance(observation_space, gym.spaces.Box) or goal_space(observation_space)):
        return (
            f"{env_id}'s observations are not supported: a vector (Box) or a goal Dict with vector {', '.join(GOAL_KEYS)} are"
        )
    with warnings.catch_warnings(action="ignore"):
        obs, _ = env.reset()  # unseeded: no run's seed is spent on a check
    boxes = observation_space.spaces if goal_space(observation_space) else {"": observation_space}
    for key, box in boxes.items():
        got = np.shape(obs[key] if key else obs)
        if key in GOAL_KEYS + ("",) and got != box.shape:
            what = f"observation {key!r}" if key else "observation"
            return (
                f"{env_id}'s reset returns an {what} of shape {got}, its observation space "
                f"declares {box.shape}: make them agree"
            )
    return None


def available_memory() -> int:
    """Bytes of memory available to a new allocation (Linux's MemAvailable, else free pages)."""
    try:
        with open("/proc/meminfo") as f:
            line = next(line for line in f if line.startswith("MemAvailable:"))
        return 1024 * int(line.split()[1])
    except (OSError, StopIteration):
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def video_refusal(env_id: str) -> str | None:
    """Why ``--capture-video`` cannot record ``env_id`` (no rgb_array frames, no moviepy, no
    OpenGL renderer for MuJoCo), or None: both tried before training starts."""
    with warnings.catch_warnings(action="ignore"):
        modes = gym.make(env_id).metadata.get("render_modes", [])
    if "rgb_array" not in modes:
        return f"--capture-video: {env_id} renders no rgb_array frames (render_modes {modes})"
    try:
        import moviepy  # noqa: F401

        env = gym.make(env_id, render_mode="rgb_array")
        env.reset(seed=0)
        env.render()
        env.close()
    except ImportError:
        return "--capture-video needs moviepy: pip install moviepy"
    except Exception as e:
        return (
            f"--capture-video: rendering {env_id} failed ({type(e).__name__}); MuJoCo needs "
            "an OpenGL backend, e.g. apt install libosmesa6 and MUJOCO_GL=osmesa"
        )
    return None
