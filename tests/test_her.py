"""common/her.py against its definition, on hand-written episodes whose every field says where
it came from: observation and achieved goal of env e, episode n, step t are [e, n, t]; the
desired goal is [e, n, -1]. Then HER's flags (which a run would ignore, which it refuses) and
common/replay.py's refusal of a buffer too small for one episode.
"""

import gymnasium as gym
import numpy as np
import pytest

from common import her, replay, tasks
from common.her import HerReplayBuffer

tasks.register_goal_tasks()


def compute_reward(achieved_goal, desired_goal):
    """Sparse, like Fetch: 0 where the goal is reached, else -1; vectorised over a batch."""
    return -np.any(achieved_goal != desired_goal, axis=-1).astype(np.float32)


def fill(buffer, lengths_per_env, steps, unfinished_tail=True):
    """Drive ``buffer.add`` like a vector env: env e runs episodes of ``lengths_per_env[e]``."""
    num_envs = len(lengths_per_env)
    ep, t = np.zeros(num_envs, int), np.zeros(num_envs, int)
    k = np.zeros(num_envs, int)  # index into each env's list of lengths
    for _ in range(steps):
        now = np.stack([[e, ep[e], t[e]] for e in range(num_envs)]).astype(np.float32)
        nxt = now + np.array([0, 0, 1], np.float32)
        length = np.array([lengths_per_env[e][k[e] % len(lengths_per_env[e])] for e in range(num_envs)])
        ended = t + 1 >= length
        goal = np.stack([[e, ep[e], -1] for e in range(num_envs)]).astype(np.float32)
        buffer.add(
            {"observation": now, "achieved_goal": now, "desired_goal": goal},
            np.zeros((num_envs, 1)),
            compute_reward(nxt, goal),
            {"observation": nxt, "achieved_goal": nxt, "desired_goal": goal},
            np.zeros(num_envs, bool),
            ended,
        )
        t = np.where(ended, 0, t + 1)
        k, ep = k + ended, ep + ended
    return ep, t


def make(size=1000, num_envs=2, k=4, strategy="future"):
    return HerReplayBuffer(
        size,
        num_envs,
        3,
        1,
        3,
        compute_reward,
        n_sampled_goal=k,
        goal_selection_strategy=strategy,
        seed=0,
    )


def episode_length(buffer, batch):
    """The length of each sampled transition's episode, read back from the stored data."""
    lengths = {}
    stored = buffer.next_achieved_goal[buffer.ep_length > 0]
    for e, n, t in stored:
        lengths[(e, n)] = max(lengths.get((e, n), 0), t)
    return np.array([lengths[(e, n)] for e, n, _ in batch["obs"]])


@pytest.mark.parametrize("strategy", ["future", "final", "episode"])
def test_relabelled_goals_come_from_the_same_episode_and_rewards_from_the_next_achieved_goal(
    strategy,
):
    buffer = make(strategy=strategy)
    fill(buffer, [[5, 7, 3], [4, 6]], 200)
    batch = buffer.sample(5000)
    obs, goal, relabelled = batch["obs"], batch["desired_goal"], batch["relabelled"]
    np.testing.assert_array_equal(batch["next_achieved_goal"], obs + [0, 0, 1])  # ag_{t+1}
    np.testing.assert_array_equal(batch["next_obs"], obs + [0, 0, 1])
    # real transitions keep their goal and reward
    np.testing.assert_array_equal(goal[~relabelled], np.c_[obs[~relabelled, :2], -np.ones(np.sum(~relabelled))])
    # relabelled goals: same env, same episode, an achieved goal ag_{j+1} at the strategy's steps
    np.testing.assert_array_equal(goal[relabelled, :2], obs[relabelled, :2])
    t, g_t, T = obs[relabelled, 2], goal[relabelled, 2], episode_length(buffer, batch)[relabelled]
    if strategy == "future":
        assert np.all((g_t >= t + 1) & (g_t <= T)) and np.any(g_t == t + 1) and np.any(g_t == T)
    elif strategy == "final":
        np.testing.assert_array_equal(g_t, T)
    else:
        assert np.all((g_t >= 1) & (g_t <= T)) and np.any(g_t <= t)
    # every reward is compute_reward(next achieved goal, goal); relabelling produces successes
    np.testing.assert_array_equal(batch["rewards"], compute_reward(batch["next_achieved_goal"], goal))
    assert np.all(batch["rewards"][~relabelled] == -1) and np.any(batch["rewards"][relabelled] == 0)


@pytest.mark.parametrize("k", [0, 1, 4, 8])
def test_relabelled_share_is_one_minus_one_over_k_plus_one(k):
    buffer = make(k=k)
    fill(buffer, [[5], [6]], 100)
    n, p = 20000, 1 - 1 / (k + 1)
    share = buffer.sample(n)["relabelled"].mean()
    assert abs(share - p) <= 4 * np.sqrt(p * (1 - p) / n) + 1e-12


def test_unfinished_episodes_are_never_sampled():
    buffer = make(k=4)
    fill(buffer, [[10], [10]], 9)
    with pytest.raises(ValueError, match="no finished episode"):
        buffer.sample(1)
    buffer = make(k=4)
    ep, t = fill(buffer, [[10], [50]], 35)  # env 0: three finished episodes and half of one; env 1: none
    assert list(ep) == [3, 0] and buffer.num_sampleable() == 30
    batch = buffer.sample(4000)
    assert np.all(batch["obs"][:, 0] == 0) and set(batch["obs"][:, 1]) == {0, 1, 2}


def test_wrap_around_with_two_envs_never_mixes_episodes():
    buffer = make(size=2 * 23, num_envs=2, k=4)  # 23 rows: episodes of 3-7 steps wrap round often
    rng = np.random.default_rng(1)
    ep, _ = fill(buffer, [list(rng.integers(3, 8, 40)), list(rng.integers(3, 8, 40))], 300)
    assert buffer.pos != 0 and ep.min() > 30
    stored = buffer.obs[buffer.ep_length > 0]
    # every stored, sampleable episode is complete: steps 0..T-1 all present
    for e, n in {(e, n) for e, n, _ in stored}:
        steps = sorted(t for e2, n2, t in stored if (e2, n2) == (e, n))
        assert steps == list(range(len(steps))), (e, n, steps)
    batch = buffer.sample(5000)
    assert set(batch["obs"][:, 0]) == {0, 1}
    relabelled = batch["relabelled"]
    np.testing.assert_array_equal(batch["desired_goal"][relabelled, :2], batch["obs"][relabelled, :2])
    assert np.all(batch["desired_goal"][relabelled, 2] > batch["obs"][relabelled, 2])
    np.testing.assert_array_equal(batch["rewards"], compute_reward(batch["next_achieved_goal"], batch["desired_goal"]))


def test_bad_configuration_is_refused():
    with pytest.raises(ValueError, match="goal_selection_strategy"):
        make(strategy="foo")
    with pytest.raises(ValueError, match="longer than the buffer"):
        fill(make(size=2 * 5, num_envs=2), [[8], [8]], 8)


def test_state_dict_round_trip_then_end_episodes_opens_the_unfinished_ones():
    """A resumed run gets the same buffer back (contents, write position, sampler state); its
    envs restart, so ``end_episodes`` ends the unfinished episodes as truncated there."""
    buffer = make(size=100, k=4)
    fill(buffer, [[10], [50]], 35)  # wraps nothing; env 0 has 5 steps unfinished, env 1 35
    copy = make(size=100, k=4)
    copy.load_state_dict(buffer.state_dict())
    for a, b in zip(buffer.sample(64).values(), copy.sample(64).values(), strict=True):
        np.testing.assert_array_equal(a, b)  # same rows and same sampler stream
    assert copy.num_sampleable() == 30
    copy.end_episodes()
    assert copy.num_sampleable() == 70 and list(copy.current_length) == [0, 0]
    batch = copy.sample(4000)
    env1 = batch["obs"][:, 0] == 1
    relabelled_from_env1 = batch["desired_goal"][env1 & batch["relabelled"]]
    assert env1.any() and set(relabelled_from_env1[:, 1]) == {0.0}  # its one, now ended, episode
    assert relabelled_from_env1[:, 2].max() <= 35  # goals only from steps that happened
    with pytest.raises(ValueError, match="shape"):
        make(size=100, num_envs=1).load_state_dict(buffer.state_dict())


def test_state_dict_holds_the_stored_rows_only_even_when_the_sampler_cache_has_their_length():
    """The cache of sampleable indices is not state: a run saved when exactly ``rows``
    transitions were sampleable (FetchPush's buffer at step 500,000) must load again, and so must
    a file that earlier code wrote with the cache in it."""
    buffer = make(size=20, num_envs=2)  # 10 rows of 2 envs
    fill(buffer, [[5], [5]], 5)  # one finished episode per env: 10 = rows sampleable
    assert buffer.num_sampleable() == buffer.rows  # the cache is filled, of length rows
    state = buffer.state_dict()
    assert not any(key.startswith("_") for key in state)
    expected = buffer.sample(32)["obs"]  # the buffer's next draw, from the saved sampler state
    for saved in (state, state | {"_sampleable": buffer.sampleable()}):
        copy = make(size=20, num_envs=2)
        copy.load_state_dict(saved)
        np.testing.assert_array_equal(copy.sample(32)["obs"], expected)


def ending_maze() -> str:
    """A goal task whose episodes end where the goal is reached: PointMaze with
    continuing_task=False, registered once."""
    if "PointMazeEnding-v3" not in gym.registry:
        spec = gym.spec("PointMaze_UMaze-v3")
        kwargs = {**spec.kwargs, "continuing_task": False}
        gym.register("PointMazeEnding-v3", spec.entry_point, max_episode_steps=300, kwargs=kwargs)
    return "PointMazeEnding-v3"


def test_hindsight_refuses_a_task_whose_termination_depends_on_the_goal():
    """HER keeps a relabelled transition's stored ``terminated``: right where termination never
    depends on the goal (Fetch), wrong where reaching the goal ends the episode (PointMaze with
    continuing_task=False), which is refused; without HER the goals are never relabelled."""
    from common.her import goal_task_reward

    ending_maze()
    with pytest.raises(ValueError, match="terminates depending on the goal"):
        goal_task_reward("PointMazeEnding-v3")
    reward = goal_task_reward("PointMazeEnding-v3", her=False)
    assert reward(np.zeros((2, 2)), np.array([[0.0, 0.0], [5.0, 5.0]])).tolist() == [1.0, 0.0]
    fetch = goal_task_reward("FetchReach-v4")
    assert fetch(np.zeros((2, 3)), np.array([[0.0, 0, 0], [1.0, 0, 0]])).tolist() == [0.0, -1.0]


def test_her_flags_a_run_would_ignore():
    """``her.ignored``: all three flags on a task without goals; k and the strategy with
    --no-her; the strategy alone at k = 0; none otherwise."""
    assert her.FLAGS.split() == ["--her", "--her-n-sampled-goal", "--her-goal-selection-strategy"]
    every, no_goals = her.FLAGS.split(), "Hopper-v5 is not a goal task"
    assert her.ignored(her.HerArgs(), "Hopper-v5", False) == dict.fromkeys(every, no_goals)
    no_her = her.ignored(her.HerArgs(her=False), "FetchReach-v4", True)
    assert no_her == dict.fromkeys(every[1:], "--no-her")
    k0 = her.ignored(her.HerArgs(her_n_sampled_goal=0), "FetchReach-v4", True)
    assert k0 == {"--her-goal-selection-strategy": "--her-n-sampled-goal 0 relabels no goal"}
    assert her.ignored(her.HerArgs(), "FetchReach-v4", True) == {}
    assert her.ignored(her.HerArgs(her=False, her_n_sampled_goal=0), "FetchReach-v4", True) == no_her


def run_args(**her_flags) -> her.HerArgs:
    """HER's flags as a script has them, beside its discount (``her.check`` reads both)."""
    args = her.HerArgs(**her_flags)
    args.gamma = 0.98
    return args


def test_her_refuses_a_negative_k_and_a_task_it_cannot_serve_and_says_when_it_is_off(capsys):
    """``her.check``: a negative k is refused (before anything else); a task without goals
    passes, with one line saying that HER is off; a goal task whose termination depends on the
    goal is refused with HER on and passes with it off; Fetch passes, silently."""
    line = "--her-n-sampled-goal must be non-negative, got -1"
    assert her.check(run_args(her_n_sampled_goal=-1), "FetchReach-v4", True) == line
    assert her.check(run_args(her_n_sampled_goal=-1), "Hopper-v5", False) == line
    assert capsys.readouterr().out == ""
    assert her.check(run_args(), "Hopper-v5", False) is None
    assert capsys.readouterr().out == "Hopper-v5 has no goals: hindsight relabelling (HER) is off\n"
    maze = ending_maze()
    assert her.check(run_args(), maze, True) == her.hindsight_refusal(maze)
    assert "terminates depending on the goal; " in her.hindsight_refusal(maze)
    assert her.check(run_args(her=False), maze, True) is None
    assert her.check(run_args(), "FetchReach-v4", True) is None
    assert capsys.readouterr().out == ""


def test_a_goal_task_without_a_batched_compute_reward_is_refused():
    """Relabelling calls ``compute_reward`` on a batch of goals: a goal task with none, or with
    one that returns a single reward for a batch, is refused (HER on or off: the critic's
    target range reads it too); the docs' example and the maze pass."""
    from toy_envs import CountingGoalEnv

    class ScalarReward(CountingGoalEnv):
        def compute_reward(self, achieved_goal, desired_goal, info):
            return -float(np.linalg.norm(achieved_goal - desired_goal) > 0.1)

    for env_class in (CountingGoalEnv, ScalarReward):
        env_id = f"{env_class.__name__}-v0"
        if env_id not in gym.registry:
            gym.register(env_id, env_class, max_episode_steps=5)
        for args in (run_args(), run_args(her=False)):
            why = her.check(args, env_id, True)
            assert why.startswith(env_id) and "compute_reward(achieved_goal, desired_goal, info)" in why
            assert "takes a batch of goals and returns one reward each" in why
    assert "returned shape () for 2 goals" in her.reward_refusal("ScalarReward-v0")
    assert her.reward_refusal("tests.point_goal:PointGoal-v0") is None
    assert her.reward_refusal("PointMaze_UMaze-v3") is None


def test_a_buffer_that_cannot_hold_one_episode_per_env_is_refused():
    """``replay.buffer_refusal``: replay samples finished episodes only, so each env's rows
    (buffer_size // num_envs) must hold the task's longest episode; a task without a time limit
    has no such bound."""
    assert replay.buffer_refusal(99, 2, "FetchReach-v4") == (
        "--buffer-size 99 keeps 49 steps per env, less than one FetchReach-v4 episode (50 steps); enlarge it"
    )
    assert replay.buffer_refusal(100, 2, "FetchReach-v4") is None  # exactly one episode each
    assert replay.buffer_refusal(1999, 2, "Hopper-v5").startswith("--buffer-size 1999 keeps 999")
    assert replay.buffer_refusal(2000, 2, "Hopper-v5") is None
    if "NoTimeLimit-v0" not in gym.registry:
        gym.register("NoTimeLimit-v0", "gymnasium.envs.classic_control:PendulumEnv")
    assert gym.spec("NoTimeLimit-v0").max_episode_steps is None
    assert replay.buffer_refusal(1, 1, "NoTimeLimit-v0") is None


def test_a_maze_reports_its_success_as_fetch_does(tmp_path):
    """The mazes put ``success`` in ``info``, not ``is_success``: training's success rate, the
    evaluation's and the run's last line carry it all the same."""
    from conftest import run_script, scalars

    result = run_script(
        "ipg_her.py",
        tmp_path,
        "--env-id",
        "PointMaze_UMaze-v3",
        "--total-timesteps",
        "600",
        "--eval-freq",
        "600",
        "--eval-episodes",
        "2",
    )
    assert result.returncode == 0, result.stderr
    (run_dir,) = tmp_path.iterdir()
    tags = scalars(run_dir)
    assert len(tags["charts/success_rate"]) == 2 and len(tags["eval/success_rate"]) == 1
    assert "success" in result.stdout.strip().splitlines()[-1]
