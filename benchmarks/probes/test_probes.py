"""The probes' own checks, each on inputs whose answer is known by hand. They run from the
project root with the tests: ``python -m pytest -q tests benchmarks/probes``."""

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]  # the project root: the probes run from there
sys.path.insert(0, str(ROOT))
import ipg_her_recipe  # noqa: E402  (slide_strikes reads the recipe's runs and critic)
import ppo_kl  # noqa: E402  (update_speed times its update)
from benchmarks.probes import (  # noqa: E402
    fetch_lifts,
    maze_paths,
    mean_bounds,
    profile_phases,
    sigma_cycle,
    slide_strikes,
    split_clip,
    update_speed,
)


def test_update_speed_times_each_full_update_and_leaves_the_first_out(monkeypatch):
    """Each timed call is one whole ppo_kl.py update, 320 Adam steps (10 epochs x 32
    minibatches, its defaults), counted on the optimiser; on a clock that ticks 2, 5 and 3 s for
    the three calls, the first (which compiles) is reported apart, and min and median are those
    of the other two (the upper one for the median of two)."""
    ticks = iter([0, 2, 2, 7, 7, 10])  # start and end of each call
    monkeypatch.setattr(update_speed, "time", SimpleNamespace(perf_counter=lambda: next(ticks)))
    update, adam_steps = ppo_kl.ppo_kl_update, []

    def counted(agent, optimizer, *rest):
        update(agent, optimizer, *rest)
        adam_steps.append(int(optimizer.state[agent.actor_logstd]["step"]))

    monkeypatch.setattr(ppo_kl, "ppo_kl_update", counted)
    timing = update_speed.time_updates("eager", update_speed.Args(repeats=2))
    assert adam_steps == [320, 640, 960]
    assert timing == {"mode": "eager", "first_s": 2, "min_s": 3, "median_s": 5, "minibatch_steps": 320}


def test_the_profile_gives_each_sample_to_its_phase():
    """py-spy's raw lines (``frame;frame;... count``) summed into the phases of the docs' tables:
    the same function (``Agent.dist``, a normaliser's ``__call__``) counts where it is called, and
    a replay buffer's writes count in either file (``HerReplayBuffer.add`` calls its base's)."""
    stacks = {
        "rollout (ppo_kl.py:151);SyncVectorEnv.step (gymnasium/vector/"
        "sync_vector_env.py:338);HopperEnv.step (gymnasium/envs/mujoco/hopper_v5.py:290)": 5,
        "rollout (ppo_kl.py:147);Agent.dist (ppo_kl.py:120);Module._call_impl (torch/nn/modules/module.py:1)": 3,
        "ppo_kl_update (ppo_kl.py:155);Agent.dist (ppo_kl.py:120)": 7,
        "rollout (ppo_kl.py:145);RunningMeanStd.update (common/normalizer.py:30)": 2,
        "RewardScaler.__call__ (common/normalizer.py:110)": 1,
        "critic_step (ipg_her.py:214);QNetwork.forward (ipg_her.py:180)": 4,
        "sample_replay (common/replay.py:130);HerReplayBuffer.sample (common/her.py:90)": 6,
        "rollout (ipg_her.py:240);ReplayBuffer.add (common/replay.py:40)": 3,
        "HerReplayBuffer.add (common/her.py:84);ReplayBuffer.add (common/replay.py:45)": 2,
        "end_iteration (common/run.py:193);finished (common/background.py:95)": 8,
        "Adam.__init__ (torch/optim/adam.py:35)": 9,
        "Run.end_iteration (common/run.py:190);SummaryWriter.add_scalar (tensorboard.py:1)": 2,
        "QNetwork.forward (ipg_her.py:180);Module._call_impl (torch/nn/modules/module.py:1)": 1,
    }
    raw = "\n".join(f"<module> (ipg_her.py:1);{stack} {n}" for stack, n in stacks.items())
    assert profile_phases.phase_samples(raw) == {
        "stepping": 5,
        "policy inference": 3,
        "policy update": 7,
        "normalisation": 2,
        "advantages and reward scaling": 1,
        "critic steps": 4,
        "replay sampling": 6,
        "replay writes": 5,
        "evaluation": 8,
        "logging and checkpoints": 2,
        "start-up and the rest": 10,
    }


def test_the_profile_of_a_tiny_run_names_its_phases(tmp_path):
    cmd = [
        sys.executable,
        "benchmarks/probes/profile_phases.py",
        "ppo_kl.py",
        "--",
        "--total-timesteps",
        "2048",
        "--num-envs",
        "2",
        "--num-steps",
        "512",
        "--eval-freq",
        "0",
        "--eval-episodes",
        "1",
        "--log-dir",
        str(tmp_path),
    ]
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = [json.loads(line) for line in out.stdout.splitlines()]
    phases = {line["phase"]: line for line in lines}
    assert {"stepping", "policy update", "all samples"} <= set(phases)
    assert 0 < phases["all samples"]["seconds"] <= phases["all samples"]["wall_s"]  # at its rate


def test_fetch_lifts_counts_a_held_lift_not_a_knock_in_time_order():
    """A lift counts when the object stays 2 cm up for 10 steps (a knock for 9 does not), and the
    replay buffer's episodes are read in time order (episode-major, the envs within)."""
    start, up = 0.425, 0.425 + 0.021
    lift = np.full(50, start)
    lift[20:30] = up
    knock = lift.copy()
    knock[29] = start
    assert fetch_lifts.held(np.array([lift, knock])).tolist() == [True, False]
    goals = np.full((100, 2, 3), start)  # two episodes for each of two envs
    goals[:50, 1, 2] = lift  # the second env's first episode: the second in time
    assert fetch_lifts.replay_lifts({"achieved_goal": goals}, parts=2) == [0.5, 0.0]
    measured = fetch_lifts.policy_by_goal(lambda obs: np.zeros(4), "FetchPickAndPlace-v4", range(4))
    assert sum(r["episodes"] for r in measured.values()) == 4
    assert all(r["held"] == 0 for r in measured.values() if r["episodes"])  # standing still


def test_slide_strikes_measures_a_slide_along_and_beside_its_line():
    """Half way to a goal 0.4 m ahead and 5 cm to its left; a goal straight along +y overshot; a
    still policy never moves the puck and never succeeds; a scripted strike slides it."""
    start = np.array([1.0, 0.5, 0.42])
    half = slide_strikes.slide_outcome(start, start + [0.4, 0, 0], start + [0.2, 0.05, 0])
    assert np.allclose(half, (0.5, 0.05))
    past = slide_strikes.slide_outcome(start, start + [0, 0.3, 0], start + [-0.02, 0.45, 0])
    assert np.allclose(past, (1.5, 0.02))
    still = slide_strikes.policy_strikes(lambda obs: np.zeros(4), range(3))
    assert still.shape == (3, 9) and still[:, 1].sum() == 0
    assert np.allclose(still[:, 2], 0, atol=1e-3) and np.all(still[:, 4:] < 1e-3)
    struck = [s for s in map(slide_strikes.scripted_strike, range(3)) if s]  # the full push
    assert struck and all(slide > 0.4 and peak > 0.03 for slide, peak, *_ in struck)
    assert all(came_in > 0.015 for _, _, came_in, *_ in struck)
    assert np.allclose([s[3:] for s in struck], (1, 1, 0))  # along the line, main axis, other
    halved = [s for s in (slide_strikes.scripted_strike(seed, push=0.5) for seed in range(3)) if s]
    assert halved and np.allclose([s[3:5] for s in halved], 0.5)  # the other axis: half its own
    assert all(0.1 < other < 0.4 for *_, other in halved)  # these lines lie off the axes


def test_slide_strikes_gain_scales_x_and_y_only_once_the_puck_has_moved():
    start = np.array([1.3, 0.75, 0.41])
    policy = lambda obs: np.array([0.6, -0.3, 0.5, 0.2], np.float32)  # noqa: E731
    act = slide_strikes.with_gain(policy, start, 1.5)
    assert np.array_equal(act({"achieved_goal": start + [0.004, 0, 0]}, 0), policy(None))
    pushed = act({"achieved_goal": start + [0.01, 0, 0]}, 1)
    assert pushed.dtype == np.float32 and np.allclose(pushed, [0.9, -0.45, 0.5, 0.2])
    assert np.allclose(
        slide_strikes.with_gain(policy, start, 2)({"achieved_goal": start + 1}, 2), [1.0, -0.6, 0.5, 0.2]
    )  # clipped to the bounds


def test_slide_strikes_reads_the_critic_at_the_step_that_moves_the_puck():
    """A critic Q = max(a_x, 0) by hand: its slope along the line is the line's x share, and
    pushing 1.2 times harder from a_x = 0.5 gains 0.1; a run's saved twin critic reads back."""
    qf = ipg_her_recipe.QNetwork(3, 4, hidden=2, low=-1.0, high=1.0)
    with torch.no_grad():
        for layer in qf.net[::2]:
            layer.weight.zero_(), layer.bias.zero_()
        qf.net[0].weight[0, 3] = qf.net[2].weight[0, 0] = qf.net[4].weight[0, 0] = 1.0  # a_x

    class Pushing:  # the policy's interface: its inputs and its action
        inputs = staticmethod(lambda obs: torch.zeros(1, 3))
        __call__ = staticmethod(lambda obs: np.array([0.5, 0, 0, 0], np.float32))

    rows = slide_strikes.critic_at_contact(qf, Pushing(), range(2))
    along = [slide_strikes.reset(gym.make("FetchSlide-v4"), seed)[3] for seed in range(2)]
    assert np.allclose(rows[:, 1], [line[0] for line in along], atol=1e-6)
    assert np.allclose(rows[:, 2], 0.1, atol=1e-6)
    assert np.allclose(rows[:, 3], [0.5 * line[0] for line in along], atol=1e-6)
    saved = ipg_her_recipe.QNetwork(24, 4, hidden=8, low=-1.0, high=1.0, twin=True)  # a run's
    content = {"args": {"hidden": 8, "twin_critic": True}, "qf": saved.state_dict()}
    x, a = torch.randn(5, 24), torch.randn(5, 4)
    assert torch.equal(slide_strikes.critic(content)(x, a, True)[1], saved(x, a, True)[1])


def test_slide_strikes_reads_far_slides_and_falls_from_the_replay_buffer_in_time_order():
    """Two envs, two episodes each: the later episode of env 0 slides 0.6 m, the earlier of env 1
    falls off the table; the rest stand still."""
    start = np.array([1.3, 0.75, 0.41])
    goals = np.tile(start, (100, 2, 1))
    after = goals.copy()
    after[50:, 0] += [0.6, 0, 0]  # env 0's second episode: a far slide
    after[:50, 1, 2] -= 0.4  # env 1's first episode: off the table
    rb = {"achieved_goal": goals, "next_achieved_goal": after}
    assert slide_strikes.replay_slides(rb, since=0) == (0.25, 0.25)
    assert slide_strikes.replay_slides(rb, since=0.5) == (0.5, 0.0)


def test_maze_paths_counts_the_cells_around_a_wall_and_groups_episodes_by_them():
    """In a 3x3 room split by a wall with one gap, the cell across the wall is 4 moves away (down,
    across the gap, up), not 2; a walled-in goal is refused; the episodes group by path length."""
    room = [[1, 1, 1, 1, 1], [1, 0, 1, 0, 1], [1, 0, 1, 0, 1], [1, 0, 0, 0, 1], [1, 1, 1, 1, 1]]
    assert maze_paths.path_length(room, (1, 1), (1, 1)) == 0
    assert maze_paths.path_length(room, (1, 1), (3, 1)) == 2
    assert maze_paths.path_length(room, (1, 1), (1, 3)) == 6
    assert maze_paths.path_length(room, (2, 1), (2, 3)) == 4
    try:
        maze_paths.path_length(room, (1, 1), (1, 2))
        raise AssertionError("a goal in a wall has no path")
    except ValueError:
        pass
    table = maze_paths.by_length([2, 6, 2, 2, 9], [1, 0, 0, 1, 0], [40, 300, -1, 60, -1])
    assert list(table) == [2, 6, 9]
    assert table[2][0] == 3 and np.allclose(table[2][1:], (2 / 3, 2 / 3, 50))  # never: not a step
    assert table[6] == (1, 0.0, 1.0, 300.0)
    assert table[9][:3] == (1, 0.0, 0.0) and np.isnan(table[9][3])


def test_sigma_cycle_bins_a_run_finds_the_entropy_troughs_and_the_evaluations_there():
    """Bins hold the steps (end - width, end] from the start on; the troughs of an entropy that
    cycles every 10 bins are its minima, a flat entropy has none; the evaluations split by them."""
    points = [[5, 1.0], [10, 3.0], [15, 5.0], [31, 7.0]]
    assert sigma_cycle.binned(points, 10) == {10: 2.0, 20: 5.0, 40: 7.0}
    assert sigma_cycle.binned(points, 10, start=10) == {20: 5.0, 40: 7.0}
    cycle = {100 * (i + 1): float(np.cos(2 * np.pi * i / 10)) for i in range(30)}
    assert sigma_cycle.troughs(cycle) == [600, 1600, 2600]  # i = 5, 15, 25: cos = -1
    assert sigma_cycle.troughs(dict.fromkeys(range(100, 1100, 100), 28.4)) == []
    evals = {10: 0.5, 20: 0.1, 30: 0.2, 40: 0.6}
    assert sigma_cycle.at_troughs(evals, [20], 10) == ([0.1, 0.2], [0.5, 0.6])
    binned = {10_000 * i: float(i % 7) for i in range(1, 31)}  # 0-6 again and again
    assert sigma_cycle.ranges(binned) == {100_000: (0.0, 6.0), 200_000: (0.0, 6.0), 300_000: (0.0, 6.0)}
    assert sigma_cycle.ranges({50_000: 3.0, 100_000: 1.0, 110_000: 5.0}) == {100_000: (1.0, 3.0), 200_000: (5.0, 5.0)}


def test_split_clip_scales_the_mean_network_with_log_sigma_or_on_its_own():
    """The policy's list (a mean network, then log sigma of shape (1, d)) is told from V's; a joint
    clip scales both by one factor, log sigma's big gradient shrinking the mean network's; split,
    each is clipped to the bound on its own."""
    mean_net, v_net = torch.nn.Linear(3, 2), torch.nn.Linear(3, 1)
    assert split_clip.is_policy([*mean_net.parameters(), torch.zeros(1, 2)])
    assert not split_clip.is_policy(list(v_net.parameters()))
    assert np.allclose(split_clip.clip_factor(3.0, 4.0, 0.5), (0.1, 0.64))
    assert split_clip.clip_factor(0.3, 0.4, 0.5)[0] == pytest.approx(1.0, abs=1e-5)
    for split, mean_after in ((False, 3.0 * 0.5 / np.hypot(3.0, 40.0)), (True, 0.5)):
        log_std = torch.zeros(1, 2, requires_grad=True)
        params = [*mean_net.parameters(), log_std]
        for p, g in zip(params, (3.0, 0.0, 40.0), strict=True):  # norms: weight, bias, sigma
            p.grad = torch.zeros_like(p)
            p.grad.view(-1)[0] = g
        split_clip.clip(split)(params, 0.5)
        assert params[0].grad.norm().item() == pytest.approx(mean_after, rel=1e-4)
        assert log_std.grad.norm().item() == pytest.approx(0.5 if split else 40 * mean_after / 3)


def test_mean_bounds_reads_the_buffer_oldest_first_and_counts_mu_beyond_either_bound():
    """A full buffer of 4 rows (2 envs) whose write position is 2: rows 2-3 are the oldest. The
    policy's mu is the observation plus its (zero) goal; bounds [-1, 1]."""
    obs = np.array([[[0.5], [3.0]], [[-2.0], [2.0]], [[0.0], [0.9]], [[-1.0], [1.5]]])  # (rows, envs, 1)
    rb = {"obs": obs, "desired_goal": 0 * obs, "actions": np.clip(obs, -1, 1), "filled": 4, "pos": 2}
    inputs = lambda raw: torch.as_tensor(raw["observation"] + raw["desired_goal"])  # noqa: E731
    policy = SimpleNamespace(actor_mean=lambda x: x, normalizer=inputs, low=-1.0, high=1.0)
    rows = mean_bounds.windows(policy, rb, global_step=108, window=4)
    assert rows == [(104, 0.25, pytest.approx(0.725)), (108, 0.75, 0.875)]  # rows 2-3 (0.0, 0.9, -1.0, 1.5), then 0-1
