"""A time limit is not a termination, in the rollouts of qprop_ppo.py, ipg_her.py and
ipg_her_recipe.py: what GAE reads keeps the two episode ends apart, so that the value target
bootstraps through a truncation (eq. 3-4), and so does what the critic replays, so that its TD
target r + gamma (1 - terminated) Q_w'(s', mu(s')) bootstraps there too (eq. 6). The truth is
the environments' own flags, recorded as they step."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from toy_envs import counting_envs

import ipg_her
import ipg_her_recipe
import qprop_ppo
from common.her import HerReplayBuffer
from common.normalizer import InputNormalizer, RunningMeanStd

SCRIPTS = {"qprop_ppo": qprop_ppo, "ipg_her": ipg_her, "ipg_her_recipe": ipg_her_recipe}
STEPS = 30


class Flags(gym.vector.VectorWrapper):
    """The vector env as it is, recording each step's ``terminated`` and ``truncated``."""

    def __init__(self, envs):
        super().__init__(envs)
        self.terminated, self.truncated = [], []

    def step(self, actions):
        obs, reward, terminated, truncated, infos = self.env.step(actions)
        self.terminated.append(terminated.copy())
        self.truncated.append(truncated.copy())
        return obs, reward, terminated, truncated, infos


def rollout(script: str):
    """``STEPS`` steps of the script's own rollout in two CountingEnvs (time limit 5; goal tasks
    for the IPG scripts, as on Fetch), with a wide policy so that some episodes terminate first.
    Returns the agent, the rollout, the policy's input where it stopped, the replay buffer and
    the envs' terminated flags ``(STEPS, 2)``."""
    module = SCRIPTS[script]
    torch.manual_seed(0)
    goal = script != "qprop_ppo"  # Q-Prop flattens a goal task; the IPG scripts keep its Dict
    envs = Flags(counting_envs(2, goal=goal))
    if goal:
        agent, norm = module.Agent(4, 1, 16), InputNormalizer(2, 2)
        reward = lambda ag, g: -np.any(ag != g, axis=-1).astype(np.float32)  # noqa: E731
        rb = HerReplayBuffer(1000, 2, 2, 1, 2, reward, n_sampled_goal=0)
    else:
        agent, norm = module.Agent(2, 1), RunningMeanStd((2,))
        rb = module.ReplayBuffer(1000, 2, 2, 1, seed=0)
    with torch.no_grad():
        agent.actor_logstd.fill_(0.5)  # actions above 0.9 terminate (after step 2)
    raw_obs, _ = envs.reset(seed=0)
    ro, raw_obs, _ = module.rollout(envs, agent, norm, raw_obs, STEPS, rb, update_norm=False)
    terminated, truncated = np.array(envs.terminated), np.array(envs.truncated)
    assert terminated.any() and truncated.any(), "both kinds of episode end, or the test is vacuous"
    return agent, ro, norm(raw_obs), rb, terminated


@pytest.mark.parametrize("script", SCRIPTS)
def test_the_value_target_bootstraps_through_a_time_limit(script):
    """With V(s) = 10 x (the step within the episode) and lam = 0, make_batch's value target is
    r + gamma V(s') where an episode goes on or hits its time limit (s' its true last state, one
    step on), and r alone where it terminated: a truncation taken for a termination drops the
    bootstrap."""
    module = SCRIPTS[script]
    agent, ro, last_obs, _, terminated = rollout(script)
    agent.get_value = lambda x: 10.0 * x[..., 1]  # the normalisation is the identity here
    gamma, step = 0.9, ro["obs"][..., 1]
    b = module.make_batch(agent, ro, last_obs, gamma, 0.0)
    target = 1.0 + gamma * torch.as_tensor(~terminated) * 10.0 * (step + 1)  # every reward: 1
    torch.testing.assert_close(b["returns"], target.flatten())


@pytest.mark.parametrize("script", SCRIPTS)
def test_the_replay_stores_a_time_limit_as_no_termination(script):
    """The critic's replay holds terminated as the environment said it, row by row: 1 where an
    episode terminated, 0 where it only hit its time limit (where the TD target must go on)."""
    *_, rb, terminated = rollout(script)
    np.testing.assert_array_equal(rb.terminations[:STEPS], terminated)
