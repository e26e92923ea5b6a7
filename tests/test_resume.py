"""--resume is exact: a run stopped at a resume point and resumed equals the run that never
stopped, scalar for scalar (the environments go on mid-episode, every generator and statistic
as it was)."""

import pytest
from conftest import run_dirs, run_script, scalars

CASES = {
    # goal task: replay, hindsight relabelling, the critic; 25 steps of 50-step episodes a rollout
    "ipg_her": (
        "FetchReach-v4",
        ["--num-steps", "25", "--critic-steps", "4", "--hidden", "16", "--eval-freq", "150", "--eval-episodes", "2"],
        150,
    ),
    # vector task: Hopper's episodes cross the resume point; reward scaling, the beta rule
    "ppo_kl": (
        "Hopper-v5",
        [
            "--num-steps",
            "64",
            "--num-minibatches",
            "2",
            "--update-epochs",
            "2",
            "--no-anneal-lr",
            "--eval-freq",
            "256",
            "--eval-episodes",
            "2",
        ],
        256,
    ),
}


@pytest.mark.parametrize("script", CASES)
def test_a_resumed_run_equals_the_run_that_never_stopped(tmp_path, script):
    env_id, flags, half = CASES[script]
    flags = [f"{script}.py", "--env-id", env_id, "--num-envs", "2", "--eval-workers", "0", "--resume-freq", str(half), *flags]
    runs = {}
    for name, budgets in (("whole", [2 * half]), ("resumed", [half, 2 * half])):
        log_dir = tmp_path / name
        for i, budget in enumerate(budgets):
            resume = ["--resume", str(run_dirs(log_dir)[0])] if i else []
            result = run_script(*flags[:1], log_dir, *flags[1:], "--total-timesteps", str(budget), *resume)
            assert result.returncode == 0, result.stderr
        (run_dir,) = run_dirs(log_dir)
        runs[name] = {tag: v for tag, v in scalars(run_dir).items() if tag != "charts/SPS"}
    assert runs["whole"]["eval/episodic_return"][-1][0] == 2 * half
    assert runs["resumed"].keys() == runs["whole"].keys()
    for tag, values in runs["whole"].items():
        assert runs["resumed"][tag] == values, tag


def vector_env(env_id: str, grasped: float = 0.0):
    import gymnasium as gym

    from common.grasped_start import GraspedStart

    def make():
        env = gym.make(env_id)
        env = GraspedStart(env, grasped) if grasped else env
        return gym.wrappers.RecordEpisodeStatistics(env)

    mode = gym.vector.AutoresetMode.SAME_STEP
    return gym.vector.SyncVectorEnv([make] * 2, autoreset_mode=mode)


@pytest.mark.parametrize(
    "env_id, grasped",
    [
        ("Hopper-v5", 0.0),
        ("FetchReach-v4", 0.0),
        ("tests.point_goal:PointGoal-v0", 0.0),
        ("PointMaze_Medium-v3", 0.0),  # its physics in an env of its own (point_env)
        ("FetchPickAndPlace-v4", 0.0),
        ("FetchPickAndPlace-v4", 0.5),
    ],
)
def test_environments_restored_in_a_new_process_go_on_as_the_originals(env_id, grasped):
    """``EnvsState`` through a file, into freshly made envs (as in a resumed process): the same
    actions give the same observations, rewards and ends, across episode ends and resets."""
    import numpy as np
    import torch

    from common import checkpoint, tasks
    from common.envs_state import EnvsState

    tasks.register_goal_tasks()
    envs = vector_env(env_id, grasped)
    envs.reset(seed=[3, 4])
    rng = np.random.default_rng(0)
    actions = [envs.action_space.sample() for _ in range(5)] + [
        rng.uniform(-1, 1, envs.action_space.shape) for _ in range(120)
    ]
    for action in actions[:5]:  # mid-episode
        envs.step(action)
    buffer = torch.serialization.io.BytesIO()
    torch.save(checkpoint.plain(EnvsState(envs).state_dict()), buffer)
    buffer.seek(0)
    saved = checkpoint.unplain(torch.load(buffer, weights_only=True))
    fresh = vector_env(env_id, grasped)
    EnvsState(fresh).load_state_dict(saved)
    for action in actions[5:]:  # past the ends of 50-step episodes, through their resets
        a, b = envs.step(action), fresh.step(action)
        for x, y in zip(a[:4], b[:4], strict=True):
            np.testing.assert_array_equal(
                np.concatenate([np.ravel(v) for v in x.values()]) if isinstance(x, dict) else x,
                np.concatenate([np.ravel(v) for v in y.values()]) if isinstance(y, dict) else y,
            )


def flat(observations):
    import numpy as np

    if isinstance(observations, dict):  # a goal task's
        return np.concatenate([np.ravel(v) for v in observations.values()])
    return observations


@pytest.mark.parametrize("env_id", ["Hopper-v5", "tests.point_goal:PointGoal-v0"])
def test_the_vector_envs_private_observations_are_its_last_ones(env_id):
    """gymnasium has no public API for a vector env's last observations, from which a resumed run
    goes on: common/envs_state.py reads and sets ``SyncVectorEnv._observations``. It must be what
    ``reset`` and every ``step`` returned, through episode ends (Hopper falls, PointGoal's
    episodes are cut at 50 steps); a gymnasium that renames it or keeps other values there fails
    here, not in a resumed run."""
    import numpy as np

    from common import tasks
    from common.envs_state import EnvsState

    tasks.register_goal_tasks()
    envs = vector_env(env_id)
    returned, _ = envs.reset(seed=[3, 4])
    np.testing.assert_array_equal(flat(envs._observations), flat(returned))
    ends = 0
    for _ in range(60):
        returned, _, terminated, truncated, _ = envs.step(envs.action_space.sample())
        np.testing.assert_array_equal(flat(envs._observations), flat(returned))
        ends += int(np.sum(terminated | truncated))
    assert ends > 0  # the autoreset's observations too
    np.testing.assert_array_equal(flat(EnvsState(envs).observations()), flat(returned))


def test_each_layer_is_saved_once_and_the_env_a_task_drives_with_them():
    """The wrappers, the task and the env it drives (the maze's ball, its physics): each once, in that order; a wrapper's
    env is also among its attributes and must not be saved twice (the resume point would hold its state twice)."""
    import gymnasium as gym

    from common import tasks
    from common.envs_state import _layers

    tasks.register_goal_tasks()
    env = gym.wrappers.RecordEpisodeStatistics(gym.make("PointMaze_Medium-v3"))
    names = [type(layer).__name__ for layer in _layers(env)]
    assert names == ["RecordEpisodeStatistics", "TimeLimit", "OrderEnforcing", "PassiveEnvChecker", "PointMazeEnv", "PointEnv"]
