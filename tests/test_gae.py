"""GAE (eq. 4), ``common/gae.py`` and each script's ``make_batch`` through it, against its
definition: the explicit discounted sum of TD residuals, stopping at an episode's end,
bootstrapping from the true last state where an episode was truncated and not where it
terminated."""

import pytest
import torch

import ipg_her
import ipg_her_recipe
import ppo_kl
import qprop_ppo
from common.gae import gae

SCRIPTS = [ppo_kl, qprop_ppo, ipg_her, ipg_her_recipe]


def explicit_gae(rewards, values, next_values, terminations, episode_ends, gamma, lam):
    """A_t = sum_{l >= 0} (gamma lam)^l delta_{t+l}, stopping after the episode's last step."""
    T, N = rewards.shape
    delta = rewards + gamma * (1 - terminations) * next_values - values
    adv = torch.zeros(T, N, dtype=torch.float64)
    for i in range(N):
        for t in range(T):
            for l in range(T - t):
                adv[t, i] += (gamma * lam) ** l * delta[t + l, i]
                if episode_ends[t + l, i]:
                    break
    return adv


def test_gae_is_the_explicit_sum_of_td_residuals():
    g = torch.Generator().manual_seed(4)
    T, N, gamma, lam = 30, 4, 0.95, 0.8
    ends = (torch.rand(T, N, generator=g) < 0.2).float()
    terminations = ends * (torch.rand(T, N, generator=g) < 0.5).float()
    rewards, values, next_values = torch.randn(3, T, N, generator=g, dtype=torch.float64)
    advantages = gae(rewards, values, next_values, terminations, ends.bool(), gamma, lam)
    expected = explicit_gae(rewards, values, next_values, terminations, ends, gamma, lam)
    torch.testing.assert_close(advantages, expected)


def batch_of(script, T, N, seed, ends, terminations, gamma, lam):
    """``script.make_batch`` on a rollout whose V is read off the observations' first entry:
    V(s_t) = obs[t, 0], V(final_obs) = final_obs[t, 0], V(last_obs) = last_obs[0]. Returns its
    advantages as (T, N), and what they must be by the explicit sum."""
    g = torch.Generator().manual_seed(seed)
    agent = script.Agent(2, 1)
    agent.get_value = lambda x: x[..., 0]
    ro = {
        "obs": torch.randn(T, N, 2, generator=g),
        "final_obs": torch.randn(T, N, 2, generator=g),
        "actions": torch.randn(T, N, 1, generator=g),
        "rewards": torch.randn(T, N, generator=g),
        "terminations": terminations,
        "episode_ends": ends,
    }
    last_obs = torch.randn(N, 2, generator=g)
    b = script.make_batch(agent, ro, last_obs, gamma, lam)
    values = ro["obs"][..., 0]
    next_values = torch.cat([values[1:], last_obs[None, :, 0]])
    next_values = torch.where(ends.bool(), ro["final_obs"][..., 0], next_values)  # true last state
    expected = explicit_gae(*(x.double() for x in (ro["rewards"], values, next_values)), terminations, ends, gamma, lam)
    return b, expected.float(), values


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda m: m.__name__)
def test_gae_matches_the_explicit_sum_with_terminations_and_truncations(script):
    g = torch.Generator().manual_seed(0)
    T, N, gamma, lam = 40, 3, 0.97, 0.9
    ends = (torch.rand(T, N, generator=g) < 0.15).float()
    terminations = ends * (torch.rand(T, N, generator=g) < 0.5).float()  # the others truncated
    assert terminations.sum() > 0 and (ends - terminations).sum() > 0
    b, expected, values = batch_of(script, T, N, 1, ends, terminations, gamma, lam)
    torch.testing.assert_close(b["advantages"], expected.flatten(), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(b["returns"], (expected + values).flatten(), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda m: m.__name__)
def test_gae_lambda_limits(script):
    """lam = 0: the one-step TD residual; lam = 1 with no episode end: the discounted return of
    the rollout, bootstrapped from V of the state it stopped in, minus V."""
    T, N, gamma = 10, 2, 0.9
    zeros = torch.zeros(T, N)
    b0, expected0, _ = batch_of(script, T, N, 2, zeros, zeros, gamma, 0.0)
    torch.testing.assert_close(b0["advantages"], expected0.flatten())
    g = torch.Generator().manual_seed(3)
    agent = script.Agent(2, 1)
    agent.get_value = lambda x: x[..., 0]
    ro = {
        "obs": torch.randn(T, N, 2, generator=g),
        "final_obs": torch.zeros(T, N, 2),
        "actions": torch.randn(T, N, 1, generator=g),
        "rewards": torch.randn(T, N, generator=g),
        "terminations": zeros,
        "episode_ends": zeros,
    }
    last_obs = torch.randn(N, 2, generator=g)
    b1 = script.make_batch(agent, ro, last_obs, gamma, 1.0)
    discounts = gamma ** torch.arange(T, dtype=torch.float32)
    mc = (discounts[:, None] * ro["rewards"]).sum(0) + gamma**T * last_obs[:, 0]
    torch.testing.assert_close(b1["advantages"].view(T, N)[0], mc - ro["obs"][0, :, 0])
